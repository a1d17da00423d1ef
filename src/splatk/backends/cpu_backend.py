"""The ``cpu`` backend: the native OpenMP ops (built on first use, see :mod:`.cpu_native`) on
CPU tensors. Rasterisers (:mod:`.cpu_native`, :mod:`.planar_cpu`), the fused projection, SH
colour and SSIM (:mod:`.fused_cpu`), the learned kernel's inference ops and the image-splat
renderer (:mod:`.image_cpu`); same values and gradients as the ``torch`` backend, whose ops it
inherits for anything it has no native version of."""
from __future__ import annotations

import torch

from ..functional.projection import Projected
from . import cpu_native
from .fused_cpu import (bf16_mlp_available, eval_sh_fused, learned_decode_fused, learned_encode_fused,
                        learned_profile_fused, project_ellipsoids_fused, ssim_mean_fused)
from .image_cpu import render_image_splats_cpu
from .planar_cpu import rasterize_planar_cpu
from .registry import register_backend
from .torch_backend import TorchBackend
from .types import PlanarProfile, Profile, RasterOutput


@register_backend("cpu")
class CpuBackend(TorchBackend):
    """Native CPU ops; ``auto`` prefers it on the CPU when the extension builds."""

    priority = 10

    @classmethod
    def unavailable_reason(cls, device: torch.device) -> str | None:
        if device.type != "cpu":
            return f"it renders CPU tensors only, not {device.type}; use --backend torch or auto"
        if not cpu_native.available():
            return f"the native extension could not be built: {cpu_native.unavailable_reason()}; use --backend torch"
        return None

    def project(self, means, quats, scales, viewmat, K, width, height, support_sigmas=3.0,
                want_view=False) -> Projected:
        return Projected(*project_ellipsoids_fused(means, quats, scales, viewmat, K, width, height,
                                                   support_sigmas=support_sigmas, want_view=want_view))

    def sh_colors(self, sh0, sh_rest, dirs, degree) -> torch.Tensor:
        return eval_sh_fused(sh0, sh_rest, dirs, degree)

    def rasterize(self, means2d, conics, opacities, colors, depths, profile: Profile, width, height,
                  background) -> RasterOutput:
        return cpu_native.rasterize_cpu(means2d, conics, opacities, colors, depths, profile, int(width),
                                        int(height), background)

    def rasterize_planar(self, means, quats, scales, opacities, colors, viewmat, K, width, height,
                         profile: PlanarProfile, background=None) -> RasterOutput:
        return rasterize_planar_cpu(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                    profile, background)

    def ssim(self, img, ref) -> torch.Tensor:
        return ssim_mean_fused(img, ref.detach())

    # the learned kernel's native ops have no backward: only when autograd is not recording
    def learned_encode(self, *args) -> torch.Tensor | None:
        return None if torch.is_grad_enabled() else learned_encode_fused(*args)

    def learned_decode(self, z2d, layers, radii2, slope) -> torch.Tensor | None:
        return None if torch.is_grad_enabled() else learned_decode_fused(z2d, layers, radii2, slope)

    def learned_profile(self, *args) -> torch.Tensor | None:
        if torch.is_grad_enabled() or not bf16_mlp_available():
            return None
        return learned_profile_fused(*args)

    def render_image_splats(self, means, chol, colors, extras, bbox, kind, aux, width,
                            height) -> torch.Tensor:
        return render_image_splats_cpu(means, chol, colors, extras, bbox, kind, aux, width, height)
