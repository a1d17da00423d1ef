"""The views a model was fitted to, kept in its file, and what a novel view asks of them.

The learned kernel's Φ_proj (paper Eq. 5) reads each primitive's distance to the camera and its
angular size. Training shows it, for each primitive, only the distances of the train cameras that
draw it. A novel view far nearer to a primitive than any of them asks Φ_proj about a distance it
never saw, and its answer there can veil the view (kangaroo's test view 1530541, decision 0121).
A drawn view therefore gives Φ_proj a primitive's distance as no nearer than the nearest train
camera that draws it: the centre in camera space scaled along its ray, so the angular size follows.
A train view draws exactly as without the hold (the camera drawing a primitive is one of those the
nearest distance runs over), so training, which never holds, and the runs it made are unchanged.

The cameras are scene data, as 3DGS's cameras.json: they are not counted in a model's footprint
(every kernel's file keeps them alike), and a file without them draws as before.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TrainView:
    """One train camera as the projection reads it."""

    world_to_cam: torch.Tensor  # [4, 4]
    K: torch.Tensor  # [3, 3]
    width: int
    height: int


@dataclass(frozen=True)
class TrainViews:
    """Poses [T, 4, 4], intrinsics [T, 4] (fx, fy, cx, cy) and sizes [T, 2] (width, height)."""

    world_to_cam: torch.Tensor
    intrinsics: torch.Tensor
    sizes: torch.Tensor

    @classmethod
    def of(cls, cameras: list) -> TrainViews:
        return cls(torch.stack([c.world_to_cam.detach().float().cpu() for c in cameras]),
                   torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in cameras], dtype=torch.float32),
                   torch.tensor([[c.width, c.height] for c in cameras], dtype=torch.int64))

    def state(self) -> dict:
        return {"world_to_cam": self.world_to_cam, "intrinsics": self.intrinsics, "sizes": self.sizes}

    @classmethod
    def from_state(cls, state: dict) -> TrainViews:
        views = cls(state["world_to_cam"], state["intrinsics"], state["sizes"])
        t = views.world_to_cam.shape[0]
        if (views.world_to_cam.shape != (t, 4, 4) or views.intrinsics.shape != (t, 4)
                or views.sizes.shape != (t, 2)):
            raise ValueError("train_views: poses, intrinsics and sizes do not describe the same cameras")
        return views

    def __len__(self) -> int:
        return self.world_to_cam.shape[0]

    def cameras(self, device: torch.device) -> list[TrainView]:
        out = []
        for pose, (fx, fy, cx, cy), (w, h) in zip(self.world_to_cam, self.intrinsics.tolist(), self.sizes.tolist()):
            K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], device=device)
            out.append(TrainView(pose.to(device), K, int(w), int(h)))
        return out


@torch.no_grad()
def nearest_drawing_distance(means, quats, scales, views: TrainViews, backend, support_sigmas: float) -> torch.Tensor:
    """[N] each primitive's camera-space distance in the nearest train view that draws it (0 where
    none does: nothing to hold it to). The projection is the one drawing uses, so in a train view
    the hold compares a distance with itself."""
    nearest = torch.full((means.shape[0],), torch.inf, device=means.device)
    for cam in views.cameras(means.device):
        proj = backend.project(means, quats, scales, cam.world_to_cam, cam.K, cam.width, cam.height,
                               support_sigmas=support_sigmas, want_view=True)
        distance = torch.linalg.vector_norm(proj.means_cam, dim=1)
        nearest = torch.where(proj.visible, torch.minimum(nearest, distance), nearest)
    return torch.where(torch.isinf(nearest), torch.zeros_like(nearest), nearest)


def hold_distance(means_cam: torch.Tensor, nearest: torch.Tensor) -> torch.Tensor:
    """``means_cam`` [M, 3] scaled along each ray to a length of at least ``nearest`` [M]; rows
    already that far are returned bit for bit (a ratio of 1 exactly)."""
    distance = torch.linalg.vector_norm(means_cam, dim=1)
    held = torch.maximum(distance, nearest)
    return means_cam * (held / distance.clamp_min(1e-30))[:, None]
