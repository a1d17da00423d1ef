"""Volumetric primitives: bounding ellipsoids plus a kernel and a colour model."""
from __future__ import annotations

from typing import NamedTuple

import torch

from ..backends import Backend, RasterOutput
from ..colors import ColorModel, make_color_model
from ..kernels import Kernel, ViewContext, make_kernel
from .base import PrimitiveModel
from .train_views import TrainViews, hold_distance, nearest_drawing_distance

#: geometric per-primitive parameters every volumetric model has (raw, pre-activation)
GEOMETRY_PARAMS = ("means", "log_scales", "quats", "opacity_logits")


class SplatModel(PrimitiveModel):
    """A scene of N volumetric primitives.

    Per-primitive tensors (first dim N) live in ``self.prims``: means [N, 3], log_scales [N, 3],
    quats [N, 4] (w, x, y, z), opacity_logits [N], plus the colour model's and the kernel's.
    Global networks (the learned kernel's MLPs) are parameters of ``self.kernel``.
    """

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        colors: torch.Tensor,
        kernel: Kernel | str = "gaussian",
        color: ColorModel | str = "sh",
        init_opacity: float = 0.5,
        scale_factor: float = 1.0,
        kernel_options: dict | None = None,
        color_options: dict | None = None,
    ) -> "SplatModel":
        """Init as DBS does: scale = sqrt(mean squared distance to the 3 nearest neighbours),
        identity rotations, opacity 0.5, base colour from the points."""
        if isinstance(kernel, str):
            kernel = make_kernel(kernel, **(kernel_options or {}))
        if isinstance(color, str):
            color = make_color_model(color, **(color_options or {}))
        n = points.shape[0]
        dist = knn_mean_sq_dist(points, k=3).clamp_min(1e-7).sqrt() * scale_factor
        prims = {
            "means": points.float().clone(),
            "log_scales": torch.log(dist)[:, None].repeat(1, 3),
            "quats": torch.cat([torch.ones(n, 1), torch.zeros(n, 3)], 1),
            "opacity_logits": torch.logit(torch.full((n,), init_opacity)),
        }
        prims.update(color.init_primitive_params(colors.float().clamp(0, 1)))
        prims.update(kernel.init_primitive_params(n, torch.device("cpu")))
        return cls(kernel, color, prims)

    #: the views the model was fitted to, from its file (None while training and in files from
    #: before them): a drawn view holds Φ_proj's distances to theirs (models/train_views.py)
    train_views: TrainViews | None = None
    _nearest_cache: tuple | None = None

    def nearest_train_distances(self, backend: Backend) -> torch.Tensor:
        """[N] :func:`nearest_drawing_distance` of the current geometry (kept until it changes)."""
        geometry = (self.prims["means"], self.prims["quats"], self.prims["log_scales"])
        key = (backend.name, self.prims["means"].device, *((id(t), t._version) for t in geometry))
        if self._nearest_cache is None or self._nearest_cache[0] != key:
            nearest = nearest_drawing_distance(self.prims["means"], self.prims["quats"], self.scales,
                                               self.train_views, backend, self.kernel.support_sigmas)
            self._nearest_cache = (key, nearest)
        return self._nearest_cache[1]

    # ---- rendering ----------------------------------------------------------------------
    def render(
        self,
        camera,
        background: torch.Tensor,
        sh_degree: int = 3,
        *,
        backend: Backend,
        colors: torch.Tensor | None = None,
    ) -> "RenderResult":
        """Render one camera with ``backend``'s ops (``splatk.backends.get``). Differentiable in
        every parameter. ``colors`` ([N, C], background [C]) replaces the colour model's output:
        what each primitive composites (a channel of ones gives blending weights)."""
        dev = self.prims["means"].device
        viewmat = camera.world_to_cam.to(dev)
        K = camera.K.to(dev)
        scales = self.scales
        proj = backend.project(self.prims["means"], self.prims["quats"], scales, viewmat, K,
                               camera.width, camera.height, support_sigmas=self.kernel.support_sigmas,
                               want_view=self.kernel.needs_view)
        idx = torch.nonzero(proj.visible).flatten()
        # index_select: its backward is index_add_, several times faster on the CPU than the
        # accumulating index_put_ that v[idx] records
        vis = {k: v.index_select(0, idx) for k, v in self.prims.items()}
        cam_center = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb = (self.color.colors(vis, vis["means"] - cam_center, sh_degree, backend) if colors is None
               else colors.index_select(0, idx))
        if not self.kernel.needs_view:
            view = ViewContext(None, None, None, backend)
        else:
            means_cam = proj.means_cam.index_select(0, idx)
            if self.train_views is not None:  # no nearer than the train views showed Φ_proj (decision 0121)
                means_cam = hold_distance(means_cam, self.nearest_train_distances(backend).index_select(0, idx))
            view = ViewContext(means_cam, scales.index_select(0, idx), proj.rotmats_cam.index_select(0, idx), backend)
        profile = self.kernel.profile(vis, view)
        means2d, conics = proj.means2d.index_select(0, idx), proj.conics.index_select(0, idx)
        if means2d.requires_grad:  # density control reads the view-space gradient (3DGS ADC)
            means2d.retain_grad()
        out: RasterOutput = backend.rasterize(
            means2d, conics,
            torch.sigmoid(vis["opacity_logits"]), rgb, proj.depths.detach().index_select(0, idx), profile,
            camera.width, camera.height, background.to(dev),
        )
        return RenderResult(out.colors, out.alphas, idx, means2d, conics)


class RenderResult(NamedTuple):
    """image [H, W, 3], alpha [H, W, 1], visible [M] indices of the rendered primitives; for
    volumetric models also their pixel-space centres [M, 2] (gradient kept after backward) and
    normalised conics [M, 3]; for planar models rendered with ``geometry=True`` the blended
    surfel geometry channels [H, W, 12] (:mod:`splatk.functional.surfel_depth`)."""

    image: torch.Tensor
    alpha: torch.Tensor
    visible: torch.Tensor
    means2d: torch.Tensor | None = None
    conics: torch.Tensor | None = None
    geometry: torch.Tensor | None = None


def knn_mean_sq_dist(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean squared distance of each point to its k nearest other points ([N])."""
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n)
    from scipy.spatial import cKDTree

    pts = points.detach().cpu().double().numpy()
    kk = min(k, n - 1)
    d, _ = cKDTree(pts).query(pts, k=kk + 1)
    d = d[:, 1:] if kk > 0 else d
    return torch.from_numpy((d**2).mean(1)).float()
