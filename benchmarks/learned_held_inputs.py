"""Would a learned run's test views gain if Phi_proj were held to the inputs the train views gave it?

    python benchmarks/learned_held_inputs.py RUN [RUN ...] [--json OUT.json] [--split train]

Phi_proj reads each primitive's distance and orientation relative to the camera. Training shows it,
for each primitive, only those of the train cameras that see the primitive (its centre in front of
the camera and in its image, as the projection decides). A test view can ask about others: a camera
nearer than any train camera, or a side none saw. Decision 0111 tried holding the inputs there, at
render time only; this script is its measurement. Every test view of each run (a `splatk fit`
folder with its model.pt, the scene loaded as the run loaded it) is drawn as fitted and then with
each visible primitive's Phi_proj inputs held:

* ``dist``: its distance to the camera clamped to the range of its distances to the train cameras
  that see it (the angular size follows, as if the camera moved along the same ray);
* ``dirT``: it is turned about its centre, as if the camera orbited it, so that the direction the
  camera sees it from lies within T degrees of the nearest of those train cameras' directions;
* ``dist+dirT``: both.

Geometry, opacity and colour are drawn as fitted. A train view draws as fitted under every
variant (``--split train`` checks it on the first four), so the runs need no retraining. Printed:
each view's PSNR as fitted and each variant's change; at the end each run's mean change.
``--json`` writes every figure.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from splatk import backends
from splatk.kernels.base import ViewContext
from splatk.metrics import psnr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gap_by_view_distance import camera_pose
from learned_donor_view import load_learned_run, visible_in

#: variant name -> (clamp the distance, largest view angle in degrees left unturned; None: no turn)
VARIANTS = {"dist": (True, None), "dir0": (False, 0.0), "dir10": (False, 10.0), "dist+dir10": (True, 10.0),
            "dist+dir5": (True, 5.0), "dist+dir0": (True, 0.0)}


def rotation_about(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """[M, 3, 3] rotations by ``angle`` [M] radians about unit ``axis`` [M, 3] (Rodrigues)."""
    x, y, z = axis.unbind(1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], 1).reshape(-1, 3, 3)
    s, c = angle.sin()[:, None, None], angle.cos()[:, None, None]
    return torch.eye(3).expand_as(k) + s * k + (1 - c) * (k @ k)


@torch.no_grad()
def train_sight(model, backend, train) -> tuple[torch.Tensor, torch.Tensor]:
    """(train camera centres [T, 3], [N, T] whether each train camera sees each primitive)."""
    centres = torch.stack([camera_pose(cam)[0] for cam in train])
    return centres, torch.stack([visible_in(model, backend, cam) for cam in train], 1)


@torch.no_grad()
def held_inputs(means, means_cam, rotmats_cam, cam, centres, sees, clamp_distance: bool,
                max_turn_deg: float | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(means_cam, rotmats_cam) of the primitives visible to ``cam`` (world ``means`` [M, 3],
    ``sees`` [M, T]) held to what the train cameras at ``centres`` that see them showed Phi_proj."""
    seen = sees.any(1)
    offsets = means[:, None, :] - centres[None]
    dist = offsets.norm(dim=2)
    if clamp_distance:
        near = torch.where(sees, dist, torch.full_like(dist, math.inf)).amin(1)
        far = torch.where(sees, dist, torch.zeros_like(dist)).amax(1)
        rho = means_cam.norm(dim=1)
        held = torch.where(seen, torch.minimum(torch.maximum(rho, near), far), rho)
        means_cam = means_cam * (held / rho)[:, None]
    if max_turn_deg is not None:
        rot = cam.world_to_cam[:3, :3]
        to_view = F.normalize(means - camera_pose(cam)[0], dim=1)
        directions = offsets / dist[:, :, None]
        cosines = torch.where(sees, (directions * to_view[:, None]).sum(2), torch.full_like(dist, -2.0))
        nearest = directions[torch.arange(len(means)), cosines.argmax(1)]
        angle = torch.acos((nearest * to_view).sum(1).clamp(-1, 1))
        turn = (angle - math.radians(max_turn_deg)).clamp(min=0) * seen
        # turning the primitive by Q, which takes the direction max_turn_deg from the nearest
        # train direction to this view's, shows it to this camera as that direction sees it
        q = rotation_about(F.normalize(torch.linalg.cross(nearest, to_view, dim=1), dim=1), turn)
        rotmats_cam = (rot @ q @ rot.T) @ rotmats_cam
    return means_cam, rotmats_cam


@torch.no_grad()
def render_held(model, backend, cam, background, centres, sees, clamp_distance: bool,
                max_turn_deg: float | None) -> torch.Tensor:
    """``cam`` drawn with the visible primitives' Phi_proj inputs held (see :func:`held_inputs`)."""
    idx = torch.nonzero(visible_in(model, backend, cam)).flatten()  # the rows render() keeps
    means, view_sees = model.prims["means"].index_select(0, idx), sees.index_select(0, idx)
    kernel = model.kernel
    fitted_profile = kernel.profile

    def held_profile(vis, view):
        means_cam, rotmats_cam = held_inputs(means, view.means_cam, view.rotmats_cam, cam, centres,
                                             view_sees, clamp_distance, max_turn_deg)
        return fitted_profile(vis, ViewContext(means_cam, view.scales, rotmats_cam, view.backend))

    kernel.profile = held_profile
    try:
        return model.render(cam, background, backend=backend).image.clamp(0, 1)
    finally:
        del kernel.profile


@torch.no_grad()
def analyse(run: Path, split: str = "test") -> dict:
    model, meta, scene, background = load_learned_run(run)
    backend = backends.get("auto", torch.device("cpu"))
    centres, sees = train_sight(model, backend, scene.train)
    views = []
    for cam in (scene.test if split == "test" else scene.train[:4]):
        target = cam.image_float()
        row = {"view": cam.name,
               "fitted": float(psnr(model.render(cam, background, backend=backend).image.clamp(0, 1), target))}
        for name, (clamp_distance, max_turn_deg) in VARIANTS.items():
            image = render_held(model, backend, cam, background, centres, sees, clamp_distance, max_turn_deg)
            row[name] = float(psnr(image, target))
        views.append(row)
    return {"run": str(run), "scene": str(meta["scene"]), "k": model.kernel.k, "split": split, "views": views}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--split", choices=("test", "train"), default="test")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        rows.append(analyse(run, args.split))
        if args.json:  # after each run: a long list can be read while it goes
            args.json.write_text(json.dumps(rows, indent=1))
    print(f"{'run':<48} {'k':>2} {'fitted':>7}" + "".join(f"{v:>11}" for v in VARIANTS))
    for r in rows:
        fitted = statistics.mean(v["fitted"] for v in r["views"])
        print(f"{r['run'][-48:]:<48} {r['k']:>2} {fitted:>7.2f}"
              + "".join(f"{statistics.mean(v[n] for v in r['views']) - fitted:>+11.3f}" for n in VARIANTS))


if __name__ == "__main__":
    main()
