"""`splatk image`: fit one photo with 2D splats at a byte budget (paper Sec. 5, image representation).

The number of primitives is ``(budget_bytes - network_bytes) // bytes_per_primitive`` (see
:func:`splatk.models.image2d.num_primitives`): the learned kernel's shared decoder (121 floats,
242 bytes at float16 and the default latent size 2) and its shape palette (64 latents of 2
floats, 256 bytes; each splat names its shape with one byte, and stores its turn in another) are
paid out of the same budget, as ``splatk bench`` does, and ``bytes`` in metrics.json counts them.
Per-splat values are float32 for every kernel; the fit rounds the shared decoder and palette to
float16 at its end, so the image it measures is the one those bytes redraw.
Training follows GaussianImage (peers.md Sec. 7.1): random init, L2 loss on the unclamped sum,
Adam; with a few hundred to a few thousand CPU iterations instead of 50k, the learning rates are
larger than its 1e-3 and decay 10x over the run (cosine).

Writes into OUT: ``render.png`` (the reconstruction), ``primitives.png`` (each splat's
1-sigma ellipse outlined in its colour), ``kernels.png`` (the kernel of the 16 largest splats
over (u, v) in [-1, 1]^2, red positive / blue negative), ``splats.bin`` (the splats as stored,
:mod:`splatk.models.image2d_io`; ``splatk image-decode`` redraws it), ``metrics.json``.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..device import resolve_device
from ..errors import InputError
from ..machine import memory_bytes
from ..option_rules import BOOL, check_value, choice, float_range, int_range, option_error
from ..outputs import OutputDir, check_output_dir
from .fit_config import MEMORY_SHARE
from ..metrics import compute_metrics, lpips_available
from ..models.image2d import (BACKENDS, KERNELS, LATENT_DIM, MAX_SHAPES, Splats2D, bytes_per_primitive,
                              decoder_floats, network_bytes, num_primitives)
from ..models.image2d_io import load_splats2d, save_splats2d


@dataclass
class ImageFitConfig:
    """Settings of `splatk image`."""

    #: 2D kernel: gaussian | gabor | learned
    kernel: str = "learned"
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
    #: Six Kodak photos at 192x128, 2000 iterations (benchmarks/results/images_palette.json,
    #: before the turn): 64 shapes vs a latent per splat, mean PSNR 25.58 vs 25.44 dB at 8 KiB,
    #: 29.63 vs 29.34 at 24 KiB (Gaussian 25.75 / 29.64), and the best LPIPS of the three.
    shapes: int = 64
    #: learned kernel with shapes: share of the iterations trained with a latent per splat
    shape_start: float = 0.5
    #: renderer: auto | cpu (native OpenMP) | torch (reference; also the exact learned mode's)
    backend: str = "auto"
    #: torch device to train on (anything but cpu renders with the torch backend)
    device: str = "cpu"
    # Learning rates, chosen for the Gaussian baseline first (kodim05 + kodim23, downscale 4, 8 and
    # 24 KiB, 2000 iterations): the shared three at 0.5x / 1x / 2x / 4x of (1e-2, 5e-2, 2e-2) gave
    # the Gaussian a mean 27.01 / 27.36 / 27.53 / 27.53 dB, so 2x. The learned decoder's rate then
    # went from 1e-2 to 2e-2 (learned kernel at the shared 1x: 27.54 -> 27.89 dB, seed 0).
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


#: the marker kind of an image output folder (``splatk.outputs``)
IMAGE_KIND = "image fit"
#: memory per photo pixel while fitting, an upper estimate: the float target, the render, its
#: gradient and the per-splat tile lists
BYTES_PER_PIXEL = 64
#: memory per splat while fitting, an upper estimate: at most 16 floats with gradient and Adam
BYTES_PER_SPLAT = 512

IMAGE_RULES = [
    ("kernel", choice(*KERNELS)), ("budget_bytes", int_range(1)), ("iters", int_range(1, 10**8)),
    ("seed", int_range(0, 2**63 - 1)), ("downscale", int_range(1, 10**4)), ("grid", int_range(2, 256)),
    ("exact", BOOL), ("latent_dim", int_range(0, 64)), ("shapes", int_range(0, MAX_SHAPES)),
    ("shape_start", float_range(0.0, 1.0)), ("backend", choice(*BACKENDS)),
    ("lr_xy", float_range(0.0)), ("lr_chol", float_range(0.0)), ("lr_color", float_range(0.0)),
    ("lr_kernel", float_range(0.0)), ("lr_net", float_range(0.0)), ("lpips", BOOL),
]


def check_image_config(cfg: ImageFitConfig, sources: dict | None = None) -> None:
    """InputError naming the first setting of ``cfg`` of the wrong type or out of range; the
    byte budget is capped by what this machine's memory can train."""
    for name, rule in IMAGE_RULES:
        check_value(name, getattr(cfg, name), rule, sources)
    cap = int(MEMORY_SHARE * memory_bytes() / BYTES_PER_SPLAT) * 4  # at least 4 bytes per splat
    if cfg.budget_bytes > cap:
        raise option_error("budget_bytes", cfg.budget_bytes, "holds more splats than this machine's memory can "
                           "train", f"give at most {cap:,} bytes", (sources or {}).get("budget_bytes"))


def load_photo(path: Path, downscale: int = 1) -> torch.Tensor:
    """[H, W, 3] float in [0, 1]; box-downscaled by an integer factor."""
    from PIL import Image

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "photo not found", "pass an existing PNG/JPEG file")
    try:
        img = Image.open(path)
        # the header's size, before any pixel is decoded: a small file may claim a huge image
        pixels_fit = int(MEMORY_SHARE * memory_bytes() / BYTES_PER_PIXEL)
        if img.width * img.height > pixels_fit:
            raise InputError(path, f"the image is {img.width} x {img.height} pixels, more than this machine's "
                             f"memory can fit ({pixels_fit:,} pixels)", "pass a smaller photo")
        img = img.convert("RGB")
    except InputError:
        raise
    except Exception as e:  # PIL raises several types for unreadable files
        raise InputError(path, f"cannot read image ({e})", "pass a PNG or JPEG photo") from e
    t = torch.from_numpy(np.asarray(img, dtype=np.float32) / 255.0)
    if downscale > 1:
        h, w = t.shape[0] // downscale * downscale, t.shape[1] // downscale * downscale
        t = t[:h, :w].reshape(h // downscale, downscale, w // downscale, downscale, 3).mean((1, 3))
    return t.contiguous()


def save_png(img: torch.Tensor, path: Path) -> None:
    from PIL import Image

    arr = (img.detach().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    Image.fromarray(arr).save(path)


def _optimizer(model: Splats2D, cfg: ImageFitConfig, s0: float) -> torch.optim.Optimizer:
    groups = [
        {"params": [model.xy_raw], "lr": cfg.lr_xy},
        {"params": [model.chol], "lr": cfg.lr_chol * s0},
        {"params": [model.colors], "lr": cfg.lr_color},
    ]
    if model.kernel == "gabor":
        groups.append({"params": [model.gabor_amps, model.gabor_freqs], "lr": cfg.lr_kernel})
    if model.kernel == "learned":
        groups.append({"params": [model.latents, model.turn], "lr": cfg.lr_kernel})
        groups.append({"params": list(model.decoder.parameters()), "lr": cfg.lr_net})
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
    # a palette of empty latents (latent_dim 0: one shared shape already) would only cost its byte
    shapes = cfg.shapes if cfg.kernel == "learned" and cfg.latent_dim > 0 else 0
    if not 0 <= shapes <= MAX_SHAPES:
        raise InputError(None, f"shapes must be 0 to {MAX_SHAPES}, got {shapes}",
                         "0 keeps a latent per splat; a palette is indexed by one byte")
    if shapes and not 0.0 <= cfg.shape_start < 1.0:
        raise InputError(None, f"shape_start must be in [0, 1), got {cfg.shape_start}")
    n = num_primitives(cfg.kernel, cfg.budget_bytes, cfg.latent_dim, shapes)
    if n < 1:
        net = network_bytes(cfg.kernel, cfg.latent_dim, shapes)
        needs = net + bytes_per_primitive(cfg.kernel, cfg.latent_dim, shapes)
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
    if cfg.backend == "cpu" and cfg.exact:
        raise InputError(None, "the exact learned mode runs on the torch backend only",
                         "drop --exact or use --backend torch")
    device = resolve_device(cfg.device, cfg.backend)
    # the init draws on the CPU generator, so a seed gives the same splats on every device
    model = Splats2D(cfg.kernel, n, h, w, grid=cfg.grid, exact=cfg.exact, generator=gen,
                     latent_dim=cfg.latent_dim, backend=cfg.backend, shapes=shapes).to(device)
    target = target.to(device)
    renderer = model.resolve_backend()  # once: every iteration draws with it
    s0 = float(model.chol[0, 0].detach())
    opt = _optimizer(model, cfg, s0)
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
        img = model.render(renderer)
        loss = ((img - target) ** 2).mean()  # L2 (GaussianImage)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_v = float(loss.detach())
        if on_step is not None:
            on_step(it, cfg.iters, loss_v, -10.0 * math.log10(max(loss_v, 1e-12)))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - t0
    model.round_shared()  # the shared decoder and palette are stored at float16
    # callers save, draw and measure on the CPU
    return model.cpu(), {"seconds": seconds, "final_loss": loss_v, "num_primitives": n}


def decode_image(splats: Path, out: Path, backend: str = "auto") -> Path:
    """Redraw the image stored in ``splats`` (a ``splats.bin``) into the PNG ``out``."""
    model = load_splats2d(splats)
    model.backend = backend
    with torch.no_grad():
        img = model.render().clamp(0, 1)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_png(img, out)
    return out


def primitives_picture(model: Splats2D, scale: int = 2) -> "object":
    """PIL image: each splat's 1-sigma ellipse outlined in its (clamped) colour on grey."""
    from PIL import Image, ImageDraw

    with torch.no_grad():
        means = model.means_px() * scale
        l11, l21, l22 = model.chol_factors()
        cols = (model.colors.clamp(0, 1) * 255).round().to(torch.uint8).tolist()
        t = torch.linspace(0, 2 * math.pi, 25)
        circ = torch.stack([torch.cos(t), torch.sin(t)], -1)  # [T, 2]
        ex = l11[:, None] * circ[None, :, 0]
        ey = l21[:, None] * circ[None, :, 0] + l22[:, None] * circ[None, :, 1]  # L @ circle
        pts = torch.stack([ex, ey], -1) * scale + means[:, None, :]
    im = Image.new("RGB", (model.width * scale, model.height * scale), (40, 40, 40))
    draw = ImageDraw.Draw(im)
    for p, c in zip(pts.tolist(), cols):
        draw.line([tuple(q) for q in p], fill=tuple(c), width=1)
    return im


def kernels_picture(model: Splats2D, count: int = 16, res: int = 48) -> "object":
    """PIL image: k(u, v) of the ``count`` largest splats on a 4-wide mosaic."""
    from PIL import Image

    with torch.no_grad():
        l11, l21, l22 = model.chol_factors()
        order = torch.argsort(l11 * l22, descending=True)[:count]
        g = torch.linspace(-1, 1, res)
        vv, uu = torch.meshgrid(g, g, indexing="ij")
        uv = torch.stack([uu, vv], -1).reshape(-1, 2)
        table = model.kernel_table() if model.kernel == "learned" else None
        tiles = []
        for i in order.tolist():
            idx = torch.full((uv.shape[0],), i, dtype=torch.long)
            k = model.kernel_values(uv, idx, table).reshape(res, res)
            k = k / k.abs().max().clamp_min(1e-8)
            rgb = torch.stack([k.clamp(min=0), torch.zeros_like(k), (-k).clamp(min=0)], -1)
            tiles.append(torch.nn.functional.pad(rgb.permute(2, 0, 1), (1, 1, 1, 1), value=0.3))
    cols = 4
    while len(tiles) % cols:
        tiles.append(torch.full_like(tiles[0], 0.3))
    rows = [torch.cat(tiles[r:r + cols], 2) for r in range(0, len(tiles), cols)]
    arr = (torch.cat(rows, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    return Image.fromarray(arr).resize((arr.shape[1] * 2, arr.shape[0] * 2), Image.NEAREST)


def run_image_fit(photo: Path, out: Path, cfg: ImageFitConfig, overwrite: bool = False,
                  on_step: Callable[[int, int, float, float], None] | None = None) -> Path:
    """Fit ``photo`` and write the artefacts into ``out``; returns ``out / "metrics.json"``."""
    out = Path(out)
    check_image_config(cfg)
    check_output_dir(out, IMAGE_KIND, overwrite, inputs=[photo])  # before any work
    target = load_photo(photo, cfg.downscale)
    model, summary = fit_image(target, cfg, on_step)
    with OutputDir(out, IMAGE_KIND, overwrite, inputs=[photo]):
        return _write_result(out, photo, target, model, summary, cfg)


def _write_result(out: Path, photo: Path, target: torch.Tensor, model, summary: dict, cfg: ImageFitConfig) -> Path:
    """Write the artefacts of a finished fit into ``out``; returns ``out / "metrics.json"``."""
    with torch.no_grad():
        img = model.render().clamp(0, 1)
    save_png(img, out / "render.png")
    save_splats2d(model, out / "splats.bin")
    primitives_picture(model).save(out / "primitives.png")
    if cfg.kernel != "gaussian":
        kernels_picture(model).save(out / "kernels.png")
    wanted = ("psnr", "ssim", "lpips") if cfg.lpips and lpips_available("alex") else ("psnr", "ssim")
    m = compute_metrics(img, target, metrics=wanted)
    m.setdefault("lpips", None)
    sizes = model.describe_bytes()
    result = {
        "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
        "bytes": sizes["bytes"], "primitive_bytes": sizes["primitive_bytes"],
        "num_primitives": summary["num_primitives"],
        "kernel": cfg.kernel, "iterations": cfg.iters, "seconds": summary["seconds"],
        "bytes_per_primitive": sizes["bytes_per_primitive"], "budget_bytes": cfg.budget_bytes,
        "network_bytes": sizes["network_bytes"],
        # the splats as stored: a 20-byte header, then exactly ``bytes`` (load_splats2d redraws them)
        "file": "splats.bin", "file_bytes": (out / "splats.bin").stat().st_size,
        "network_floats": decoder_floats(cfg.latent_dim) if cfg.kernel == "learned" else 0,
        "latent_dim": cfg.latent_dim if cfg.kernel == "learned" else 0,
        "shapes": model.shapes,
        "image": str(photo), "height": int(target.shape[0]), "width": int(target.shape[1]),
        "config": asdict(cfg),
    }
    path = out / "metrics.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path
