"""The fit loop of `splatk image`: splats fitted to one photo at a byte budget.

The number of primitives is ``(budget_bytes - network_bytes) // bytes_per_primitive`` (see
:func:`splatk.image.bytes.num_primitives`): the learned kernel's shared decoder (121 floats,
242 bytes at float16 and the default latent size 2) and its shape palette (64 latents of 2
floats, 256 bytes; each splat names its shape with one byte, and stores its turn in another) are
paid out of the same budget, as ``splatk bench`` does, and ``bytes`` in metrics.json counts them.
Per-splat values are float32 for every kernel; the fit rounds the shared decoder and palette to
float16 at its end, so the image it measures is the one those bytes redraw.
``mode``: ``tuned`` (default) is splatk's image mode as above; ``paper`` is the paper's image
setting: ``learned`` becomes the paper's planar kernel (``learned-paper``: a 10-float latent per
splat, a sigmoid decoder pretrained on the Gaussian surfel, no envelope, turn or palette) and the
budget counts the primitives only, as the paper's comparison with GabSplat does. The other
kernels have no shared part, so both modes give them the same splats.
Training follows GaussianImage (peers.md Sec. 7.1): random init, L2 loss on the unclamped sum,
Adam; with a few hundred to a few thousand CPU iterations instead of 50k, the learning rates are
larger than its 1e-3 and decay 10x over the run (cosine).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import torch

from ..device import resolve_device
from ..errors import InputError
from .bytes import MAX_SHAPES, bytes_per_primitive, counted_network_bytes, num_primitives
from .kernels import KERNELS, LATENT_DIM, PAPER_LATENT_DIM, image_kernel
from .model import BACKENDS, Splats2D


@dataclass
class ImageFitConfig:
    """Settings of `splatk image`."""

    #: 2D kernel: gaussian | gabor | gabsplat | learned
    kernel: str = "learned"
    #: tuned (splatk's learned kernel: palette, turn, envelope; shared part paid from the budget)
    #: or paper (the paper's planar learned kernel and its byte count: primitives only)
    mode: str = "tuned"
    #: bytes for all per-primitive parameters (float32)
    budget_bytes: int = 65536
    #: optimisation steps
    iters: int = 2000
    #: random seed of the init
    seed: int = 0
    #: downscale the photo by this integer factor first (box filter)
    downscale: int = 1
    #: learned kernel: table nodes per axis (bilinear lookup at render time)
    grid: int = 8
    #: learned kernel: evaluate the decoder per pixel instead of the table (slow reference)
    exact: bool = False
    #: learned kernel: floats of each primitive's latent (fewer floats = more primitives per byte;
    #: 0 = one learned shape shared by all splats)
    latent_dim: int = LATENT_DIM
    #: learned kernel: size of the shape palette (0 = a latent per splat; K = K shared latents
    #: and a one-byte index per splat, k-means of the latents at ``shape_start`` of the run).
    #: 64 shapes beat a latent per splat on the six Kodak photos at both budgets, with the best
    #: LPIPS of the three (docs/decisions/0008-image-learned-kernel.md).
    shapes: int = 64
    #: learned kernel with shapes: share of the iterations trained with a latent per splat
    shape_start: float = 0.5
    #: renderer: auto | cpu (native OpenMP) | torch (reference; also the exact learned mode's)
    backend: str = "auto"
    #: torch device to train on (anything but cpu renders with the torch backend)
    device: str = "cpu"
    # Learning rates, chosen for the Gaussian baseline first (kodim05 + kodim23): 2x of
    # (1e-2, 5e-2, 2e-2) for the shared three, then 2e-2 for the learned decoder
    # (docs/decisions/0008-image-learned-kernel.md).
    #: Adam learning rate of the means (tanh space: 2e-2 is about W/100 px per step)
    lr_xy: float = 2e-2
    #: Adam learning rate of the Cholesky factors, relative to the initial sigma
    lr_chol: float = 1e-1
    #: Adam learning rate of the colours
    lr_color: float = 4e-2
    #: Adam learning rate of the kernel parameters (Gabor waves, learned latents and turns)
    lr_kernel: float = 3e-2
    #: Adam learning rate of the learned kernel's decoder
    lr_net: float = 2e-2
    #: compute LPIPS (alex) when its weights are available
    lpips: bool = True



MODES = ("tuned", "paper")


def resolve_mode(cfg: ImageFitConfig) -> tuple[str, int, int]:
    """(kernel, latent_dim, shapes) that ``cfg`` fits: in paper mode ``learned`` is the paper's
    planar kernel with its 10-float latent and no palette."""
    if cfg.mode not in MODES:
        raise InputError(None, f"unknown mode {cfg.mode!r}", f"choose from {', '.join(MODES)}")
    if cfg.mode == "paper" and cfg.kernel == "learned":
        return "learned-paper", PAPER_LATENT_DIM, 0
    # a palette of empty latents (latent_dim 0: one shared shape already) would only cost its byte
    shapes = cfg.shapes if cfg.kernel == "learned" and cfg.latent_dim > 0 else 0
    return cfg.kernel, cfg.latent_dim, shapes


def _optimizer(model: Splats2D, cfg: ImageFitConfig, s0: float) -> torch.optim.Optimizer:
    groups = [{"params": [model.xy_raw], "lr": cfg.lr_xy}]
    groups += model.kernel2d.geometry_groups(model, cfg.lr_chol * s0, cfg.lr_kernel)
    groups += [{"params": [model.colors], "lr": cfg.lr_color}]
    groups += model.kernel2d.param_groups(model, cfg.lr_kernel, cfg.lr_net)
    for g in groups:
        g["base_lr"] = g["lr"]
    return torch.optim.Adam(groups)


def fit_image(target: torch.Tensor, cfg: ImageFitConfig,
              on_step: Callable[[int, int, float, float], None] | None = None) -> tuple[Splats2D, dict]:
    """Fit splats to ``target`` [H, W, 3]; returns the model and a summary (psnr, seconds...)."""
    if cfg.kernel not in KERNELS:
        raise InputError(None, f"unknown kernel {cfg.kernel!r}", f"choose from {', '.join(KERNELS)}")
    if cfg.kernel == "learned" and cfg.latent_dim < 0:
        raise InputError(None, f"latent_dim must be >= 0, got {cfg.latent_dim}")
    kernel, latent_dim, shapes = resolve_mode(cfg)
    if not 0 <= shapes <= MAX_SHAPES:
        raise InputError(None, f"shapes must be 0 to {MAX_SHAPES}, got {shapes}",
                         "0 keeps a latent per splat; a palette is indexed by one byte")
    if shapes and not 0.0 <= cfg.shape_start < 1.0:
        raise InputError(None, f"shape_start must be in [0, 1), got {cfg.shape_start}")
    n = num_primitives(kernel, cfg.budget_bytes, latent_dim, shapes)
    if n < 1:
        net = counted_network_bytes(kernel, latent_dim, shapes)
        needs = net + bytes_per_primitive(kernel, latent_dim, shapes)
        paid = f" after its {net}-byte shared decoder{' and palette' if shapes else ''}" if net else ""
        raise InputError(None, f"budget of {cfg.budget_bytes} bytes holds no {cfg.kernel} primitive{paid}",
                         f"raise --budget-bytes to at least {needs}")
    if cfg.iters < 0:
        raise InputError(None, f"iters must be >= 0, got {cfg.iters}")
    h, w = target.shape[:2]
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    if cfg.backend not in BACKENDS:
        raise InputError(None, f"unknown backend {cfg.backend!r}", f"choose from {', '.join(BACKENDS)}")
    if cfg.backend == "cpu" and not image_kernel(kernel).has_native:
        raise InputError(None, f"the {kernel} kernel runs on the torch backend only",
                         "use --backend auto or torch")
    if cfg.backend == "cpu" and cfg.exact:
        raise InputError(None, "the exact learned mode runs on the torch backend only",
                         "drop --exact or use --backend torch")
    device = resolve_device(cfg.device, cfg.backend)
    # the init draws on the CPU generator, so a seed gives the same splats on every device
    model = Splats2D(kernel, n, h, w, grid=cfg.grid, exact=cfg.exact, generator=gen,
                     latent_dim=latent_dim, backend=cfg.backend, shapes=shapes)
    model.kernel2d.prepare(model, gen)  # the paper kernel's pretraining, on the CPU
    model = model.to(device)
    target = target.to(device)
    renderer = model.resolve_backend()  # once: every iteration draws with it
    opt = _optimizer(model, cfg, model.s0)
    t0 = time.perf_counter()
    loss_v = float("nan")
    # the palette replaces the latents before this iteration (round: 0 -> from the start)
    palette_at = 1 + round(cfg.shape_start * cfg.iters) if shapes else None
    if shapes and cfg.iters == 0:
        model.quantize_shapes(gen)
    for it in range(1, cfg.iters + 1):
        if it == palette_at:
            model.quantize_shapes(gen)
            opt.add_param_group({"params": [model.palette], "lr": cfg.lr_kernel, "base_lr": cfg.lr_kernel})
        frac = (it - 1) / max(cfg.iters, 1)
        scale = 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * frac))  # cosine decay to 0.1x
        for g in opt.param_groups:
            g["lr"] = g["base_lr"] * scale
        model.kernel2d.before_step(model, frac, gen)
        img = model.render(renderer)
        mse = ((img - target) ** 2).mean()  # L2 (GaussianImage)
        loss = mse + model.kernel2d.regularization(model)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_v = float(mse.detach())
        if on_step is not None:
            on_step(it, cfg.iters, loss_v, -10.0 * math.log10(max(loss_v, 1e-12)))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - t0
    model.kernel2d.before_step(model, 1.0, gen)  # what is stored: no exploring waves
    model.round_shared()  # the shared decoder and palette are stored at float16
    # callers save, draw and measure on the CPU
    return model.cpu(), {"seconds": seconds, "final_loss": loss_v, "num_primitives": n, "kernel": kernel}
