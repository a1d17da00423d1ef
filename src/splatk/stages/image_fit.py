"""`splatk image`: fit one photo with 2D splats at a byte budget (paper Sec. 5, image representation).

The representation, its byte accounting, file and fit loop are the :mod:`splatk.image` package
(:func:`splatk.image.fit.fit_image`); this stage checks the settings, reads the photo and writes
the results.

Writes into OUT: ``render.png`` (the reconstruction), ``primitives.png`` (each splat's
1-sigma ellipse outlined in its colour), ``kernels.png`` (the kernel of the 16 largest splats
over (u, v) in [-1, 1]^2, red positive / blue negative), ``splats.bin`` (the splats as stored,
:mod:`splatk.image.file`; ``splatk image-decode`` redraws it), ``metrics.json``.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..errors import InputError
from ..machine import memory_bytes
from ..option_rules import BOOL, check_value, choice, float_range, int_range, option_error
from ..outputs import OutputDir, check_output_dir
from .fit_memory import MEMORY_SHARE
from ..metrics import compute_metrics, lpips_available
from ..image.bytes import MAX_SHAPES
from ..image.file import load_splats2d, save_splats2d
from ..image.fit import MODES, ImageFitConfig, fit_image
from ..image.kernels import KERNELS, decoder_floats
from ..image.model import BACKENDS
from ..image.pictures import kernels_picture, primitives_picture


#: the marker kind of an image output folder (``splatk.outputs``)
IMAGE_KIND = "image fit"
#: memory per photo pixel while fitting, an upper estimate: the float target, the render, its
#: gradient and the per-splat tile lists
BYTES_PER_PIXEL = 64
#: memory per splat while fitting, an upper estimate: at most 16 floats with gradient and Adam
BYTES_PER_SPLAT = 512

IMAGE_RULES = [
    ("kernel", choice(*KERNELS)), ("mode", choice(*MODES)), ("budget_bytes", int_range(1)), ("iters", int_range(1, 10**8)),
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
        # what the budget paid for: ``bytes`` less the decoder in paper mode (primitives only)
        "counted_bytes": sizes["counted_bytes"],
        "num_primitives": summary["num_primitives"],
        "kernel": model.kernel, "mode": cfg.mode, "iterations": cfg.iters, "seconds": summary["seconds"],
        "bytes_per_primitive": sizes["bytes_per_primitive"], "budget_bytes": cfg.budget_bytes,
        "network_bytes": sizes["network_bytes"],
        # the splats as stored: a 20-byte header, then exactly ``bytes`` (load_splats2d redraws them)
        "file": "splats.bin", "file_bytes": (out / "splats.bin").stat().st_size,
        "network_floats": decoder_floats(model.latent_dim) if model.kernel2d.decoded else 0,
        "latent_dim": model.latent_dim if model.kernel2d.decoded else 0,
        "shapes": model.shapes,
        "image": str(photo), "height": int(target.shape[0]), "width": int(target.shape[1]),
        "config": asdict(cfg),
    }
    path = out / "metrics.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    return path
