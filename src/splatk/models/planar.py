"""Planar primitives (2DGS-style surfels): oriented disks plus a planar kernel and a colour model.

Same interface as :class:`splatk.models.volumetric.SplatModel` (the trainer, MCMC, save/load and
eval treat both alike); the differences are two scales per primitive (the disk's in-plane
sigmas, ``log_scales`` [N, 2]), the rasteriser (the backend's ``rasterize_planar``)
and the kernels (registered as ``("planar", name)``, :mod:`splatk.kernels.planar`).
"""
from __future__ import annotations

import torch
from torch import nn

from ..backends import Backend
from ..colors import ColorModel, make_color_model
from ..functional.planar import planar_in_front
from ..functional.projection import quats_to_rotmats
from ..functional.surfel_depth import GEOMETRY_CHANNELS, surfel_geometry_channels
from ..kernels import Kernel, ViewContext, make_kernel
from .base import PrimitiveModel
from .volumetric import RenderResult, knn_mean_sq_dist


class PlanarModel(PrimitiveModel):
    """A scene of N planar primitives.

    ``self.prims``: means [N, 3], log_scales [N, 2], quats [N, 4] (w, x, y, z; columns 0 and 1
    of the rotation span the disk, column 2 is its normal), opacity_logits [N], plus the colour
    model's and the kernel's per-primitive parameters.
    """

    primitive = "planar"

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
    ) -> "PlanarModel":
        """As :meth:`SplatModel.from_points` (neighbour-spacing scales, opacity 0.5), except the
        rotations: random (from torch's global RNG), as 2DGS does, since identity rotations
        would turn every disk edge-on to views along the world x and y axes."""
        if isinstance(kernel, str):
            kernel = make_kernel(kernel, "planar", **(kernel_options or {}))
        if isinstance(color, str):
            color = make_color_model(color, **(color_options or {}))
        n = points.shape[0]
        dist = knn_mean_sq_dist(points, k=3).clamp_min(1e-7).sqrt() * scale_factor
        prims = {
            "means": points.float().clone(),
            "log_scales": torch.log(dist)[:, None].repeat(1, 2),
            "quats": nn.functional.normalize(torch.randn(n, 4), dim=-1),
            "opacity_logits": torch.logit(torch.full((n,), init_opacity)),
        }
        prims.update(color.init_primitive_params(colors.float().clamp(0, 1)))
        prims.update(kernel.init_primitive_params(n, torch.device("cpu")))
        return cls(kernel, color, prims)

    # ---- accessors (the rest: PrimitiveModel; scales are the [N, 2] in-plane sigmas) ------
    @property
    def scales_3d(self) -> torch.Tensor:
        """[N, 3] scales with 0 along the normal: a disk has no thickness (used for the shape of
        MCMC's position noise, which so stays in each disk's plane)."""
        s = self.scales
        return torch.cat([s, torch.zeros_like(s[:, :1])], 1)

    # ---- rendering ----------------------------------------------------------------------
    def render(self, camera, background: torch.Tensor, sh_degree: int = 3, *,
               backend: Backend, colors: torch.Tensor | None = None, geometry: bool = False) -> RenderResult:
        """Render one camera with ``backend``'s ops; differentiable in every parameter.
        ``colors`` ([N, C]) replaces the colour model's output, as in ``SplatModel.render``.
        ``visible`` lists the drawn primitives (in front of the camera, see
        :func:`~splatk.functional.planar.planar_in_front`) in index order. ``geometry``: also
        composite each surfel's normal and inverse-depth channels in the same rasteriser call
        (on background 0), returned as ``RenderResult.geometry`` [H, W, 12]."""
        dev = self.prims["means"].device
        viewmat = camera.world_to_cam.to(dev)
        K = camera.K.to(dev)
        idx = torch.nonzero(planar_in_front(self.prims["means"], self.prims["quats"], self.scales,
                                            viewmat)).flatten()
        vis = {k: v.index_select(0, idx) for k, v in self.prims.items()}
        scales = torch.exp(vis["log_scales"])
        cam_center = -viewmat[:3, :3].T @ viewmat[:3, 3]
        rgb = (self.color.colors(vis, vis["means"] - cam_center, sh_degree, backend) if colors is None
               else colors.index_select(0, idx))
        if self.kernel.needs_view:
            rw, tw = viewmat[:3, :3], viewmat[:3, 3]
            view = ViewContext(vis["means"] @ rw.T + tw, scales, rw @ quats_to_rotmats(vis["quats"]), backend)
        else:
            view = ViewContext(None, None, None, backend)
        profile = self.kernel.profile(vis, view)
        background = background.to(dev)
        channels = rgb.shape[-1]
        if geometry:
            rgb = torch.cat([rgb, surfel_geometry_channels(vis["means"], vis["quats"], viewmat).to(rgb.dtype)], -1)
            background = torch.cat([background, background.new_zeros(GEOMETRY_CHANNELS)])
        out = backend.rasterize_planar(vis["means"], vis["quats"], scales, torch.sigmoid(vis["opacity_logits"]),
                                       rgb, viewmat, K, camera.width, camera.height, profile, background)
        if not geometry:
            return RenderResult(out.colors, out.alphas, idx)
        return RenderResult(out.colors[..., :channels], out.alphas, idx, geometry=out.colors[..., channels:])
