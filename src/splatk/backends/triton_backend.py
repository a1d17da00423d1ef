"""The ``cuda`` backend: tile kernels in Triton on CUDA tensors, for splats
(:mod:`.triton_raster`), planar splats (:mod:`.triton_planar`) and the 2D image splats
(:mod:`.triton_image`).

Projection, SH colour and SSIM stay the ``torch`` backend's ops on the device (inherited: no
host round trips). Under Triton's interpreter
(``TRITON_INTERPRET=1``) the same kernels run on CPU tensors, which is how they are tested
without a GPU; ``auto`` prefers the native ``cpu`` backend there.

One render: per-primitive tile ranges from the support ellipse's pixel box, one (tile, depth
rank) key per (primitive, tile) pair sorted on the device (a radix sort on CUDA), per-tile
ranges by ``searchsorted``, then one program per 16x16 tile forward and backward. The only
host synchronisation is the number of pairs, which sizes the pair buffers.
"""
from __future__ import annotations

import importlib.util
import os

import torch

from .registry import register_backend
from .torch_backend import TorchBackend
from .triton_binning import bin_pairs
from .types import T_MIN, PlanarProfile, Profile, RasterOutput

#: colour channels the kernels take (a padded vector of lanes); more falls back to torch
MAX_CHANNELS = 64


def interpreter_enabled() -> bool:
    """Whether Triton runs its kernels in the interpreter (on CPU tensors)."""
    return os.environ.get("TRITON_INTERPRET", "0").lower() in ("1", "true", "on", "yes")


def triton_missing_reason() -> str | None:
    if importlib.util.find_spec("triton") is None:
        return "Triton is not installed; pip install 'splatk[gpu]' (CUDA builds of torch bring it)"
    return None


class _TritonRasterize(torch.autograd.Function):
    """Forward and backward kernels of one render; gradients for every float input."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, params, background, depths, kind, k,
                width, height):
        from . import triton_raster as tr

        device, channels = means2d.device, colors.shape[1]
        means2d, conics, opacities, colors, params, background = (
            t.detach().contiguous() for t in (means2d, conics, opacities, colors, params, background))
        flat_ids, tile_offsets, tiles_x = bin_pairs(means2d, conics, depths.detach(), width, height)
        num_tiles = tile_offsets.numel() - 1
        img = torch.empty(height * width, channels, device=device, dtype=torch.float32)
        t_final = torch.empty(height * width, device=device, dtype=torch.float32)
        n_contrib = torch.empty(height * width, device=device, dtype=torch.int32)
        consts = tr.launch_constants(kind, k, channels)
        tr.rasterize_fwd_kernel[(num_tiles,)](
            means2d, conics, opacities, colors, params, background, tile_offsets, flat_ids,
            img, t_final, n_contrib, width, height, tiles_x, channels, T_STOP=T_MIN, **consts)
        ctx.save_for_backward(means2d, conics, opacities, colors, params, background, tile_offsets,
                              flat_ids, t_final, n_contrib)
        ctx.meta = (kind, k, width, height, tiles_x)
        return img.view(height, width, channels), (1.0 - t_final).view(height, width, 1)

    @staticmethod
    def backward(ctx, v_img, v_alpha):
        from . import triton_raster as tr

        (means2d, conics, opacities, colors, params, background, tile_offsets, flat_ids, t_final,
         n_contrib) = ctx.saved_tensors
        kind, k, width, height, tiles_x = ctx.meta
        channels = colors.shape[1]
        v_img = v_img.contiguous().view(height * width, channels)
        v_alpha = v_alpha.contiguous().view(height * width)
        g_means, g_conics = torch.zeros_like(means2d), torch.zeros_like(conics)
        g_opac, g_colors, g_params = (torch.zeros_like(opacities), torch.zeros_like(colors),
                                      torch.zeros_like(params))
        consts = tr.launch_constants(kind, k, channels)
        tr.rasterize_bwd_kernel[(tile_offsets.numel() - 1,)](
            means2d, conics, opacities, colors, params, background, tile_offsets, flat_ids, t_final,
            n_contrib, v_img, v_alpha, g_means, g_conics, g_opac, g_colors, g_params,
            width, height, tiles_x, channels, KP=_next_pow2(k), **consts)
        g_background = (v_img * t_final[:, None]).sum(0)
        g_params = g_params if ctx.needs_input_grad[4] else None
        return g_means, g_conics, g_opac, g_colors, g_params, g_background, None, None, None, None, None


def _next_pow2(x: int) -> int:
    return 1 << max(0, (int(x) - 1).bit_length())


def rasterize_triton(means2d, conics, opacities, colors, depths, profile: Profile, width: int,
                     height: int, background) -> RasterOutput:
    """The Triton tile rasteriser (float32); same contract and gradients as ``rasterize_torch``."""
    n = means2d.shape[0]
    if profile.kind == "gaussian" or profile.params is None:
        params, k = torch.zeros(max(n, 1), 1, device=means2d.device, dtype=torch.float32), 1
    else:
        params, k = profile.params, profile.params.shape[1]
    colors_out, alphas = _TritonRasterize.apply(
        means2d, conics, opacities, colors, params, background.to(colors.dtype), depths, profile.kind,
        k, int(width), int(height))
    return RasterOutput(colors_out, alphas)


@register_backend("cuda")
class TritonBackend(TorchBackend):
    """Triton kernels on CUDA tensors; every op it has no kernel for is the torch backend's.

    Float32 renders with at most ``MAX_CHANNELS`` colour channels run the Triton rasterisers;
    other dtypes and channel counts (and a render with no pixels) use the torch ones.
    """

    # above torch (auto takes it on CUDA devices), below the native cpu backend (with the
    # interpreter enabled on a CPU machine, auto still takes the native one there)
    priority = 5

    @classmethod
    def unavailable_reason(cls, device: torch.device) -> str | None:
        missing = triton_missing_reason()
        if missing is not None:
            return missing
        if device.type == "cuda":
            return None
        if device.type == "cpu" and interpreter_enabled():
            return None
        return (f"it renders CUDA tensors only, not {device.type}; use --backend cpu, torch or auto "
                "(TRITON_INTERPRET=1 runs its kernels on the CPU, slowly, for testing)")

    def rasterize(self, means2d, conics, opacities, colors, depths, profile: Profile, width, height,
                  background) -> RasterOutput:
        floats = [means2d, conics, opacities, colors] + ([profile.params] if profile.params is not None else [])
        if (any(t.dtype != torch.float32 for t in floats) or not 1 <= colors.shape[1] <= MAX_CHANNELS
                or int(width) * int(height) == 0):
            return super().rasterize(means2d, conics, opacities, colors, depths, profile, width, height,
                                     background)
        return rasterize_triton(means2d, conics, opacities, colors, depths, profile, width, height,
                                background)

    def rasterize_planar(self, means, quats, scales, opacities, colors, viewmat, K, width, height,
                         profile: PlanarProfile, background=None) -> RasterOutput:
        floats = [means, quats, scales, opacities, colors, viewmat, K]
        grid_ok = profile.kind != "grid" or (profile.table is not None and profile.table.dim() == 3
                                             and profile.table.shape[-1] >= 2)
        if profile.table is not None:
            floats.append(profile.table)
        if (any(t.dtype != torch.float32 for t in floats) or not 1 <= colors.shape[1] <= MAX_CHANNELS
                or profile.kind not in ("gaussian_surfel", "grid") or not grid_ok
                or int(width) * int(height) == 0):
            return super().rasterize_planar(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                            profile, background)
        from .triton_planar import rasterize_planar_triton

        if background is None:
            background = torch.zeros(colors.shape[1], device=colors.device, dtype=colors.dtype)
        return rasterize_planar_triton(means, quats, scales, opacities, colors, viewmat, K, int(width),
                                       int(height), profile, background)

    def render_image_splats(self, means, chol, colors, extras, bbox, kind, aux, width, height) -> torch.Tensor:
        from .triton_image import render_image_splats_triton

        return render_image_splats_triton(means, chol, colors, extras, bbox, kind, aux, width, height)
