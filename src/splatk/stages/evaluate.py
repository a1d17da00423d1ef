"""`splatk eval`: render the held-out views of a run and measure them.

Writes RUN/metrics.json (the train split: RUN/metrics_train.json, so measuring the fit to the train
views never replaces the held-out figures): ``mean`` (psnr, ssim, lpips), ``per_view`` values,
``num_primitives``, ``footprint_mb``, ``render_ms`` (median per view, wall clock, this machine) and
how it was measured (backend, threads, LPIPS network).
"""
from __future__ import annotations

import json
import statistics
import time
from pathlib import Path
from typing import Callable

import torch

from .. import backends
from ..data import load_scene
from ..device import resolve_device
from ..errors import InputError
from ..metrics import compute_metrics
from ..models.io import load_model


def run_eval(
    run: str | Path,
    metrics: tuple[str, ...] = ("psnr", "ssim"),
    lpips_net: str = "alex",
    backend: str = "auto",
    scene_path: str | Path | None = None,
    split: str = "test",
    save_renders: bool = False,
    device: str = "cpu",
    on_view: Callable[[int, int], None] | None = None,
) -> dict:
    run = Path(run)
    dev = resolve_device(device, backend)
    renderer = backends.get(backend, dev)  # resolved once for every view
    model, meta = load_model(run / "model.pt")
    model = model.to(dev)
    scene_path = scene_path or meta.get("scene")
    if not scene_path or not Path(scene_path).exists():
        raise InputError(scene_path or run, "scene folder of this run not found", "pass --scene")
    scene = load_scene(scene_path, downscale=meta.get("downscale", 1.0),
                       test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
    cams = scene.test if split == "test" else scene.train
    if not cams:
        fix = ("the run was fitted with --eval-split none; use --split train" if meta.get("eval_split") == "none"
               else "use --split train")
        raise InputError(scene_path, f"the scene has no {split} views", fix)
    bg = torch.tensor(scene.background, dtype=torch.float32, device=dev)
    per_view, times, warnings = [], [], list(scene.warnings)
    render_dir = run / "renders" / split
    if save_renders:
        render_dir.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        model.render(cams[0], bg, backend=renderer)  # warm-up (caches)
        for i, cam in enumerate(cams):
            t0 = time.perf_counter()
            out = model.render(cam, bg, backend=renderer)
            if dev.type == "cuda":  # the render is asynchronous there
                torch.cuda.synchronize(dev)
            times.append((time.perf_counter() - t0) * 1000)
            img = out.image.clamp(0, 1)
            m = compute_metrics(img, cam.image_float(dev), metrics, lpips_net=lpips_net,
                                mask=cam.mask_float(dev))
            warnings += m.pop("warnings", [])
            per_view.append({"view": cam.name, **m})
            if save_renders:
                from .export import write_png

                write_png(render_dir / f"{Path(cam.name).stem}.png", img.cpu())
            if on_view:
                on_view(i + 1, len(cams))
    keys = [k for k in metrics if all(v.get(k) is not None for v in per_view)]
    mean = {k: float(sum(v[k] for v in per_view) / len(per_view)) for k in keys}
    for k in metrics:
        mean.setdefault(k, None)
    result = {
        "run": str(run),
        "split": split,
        "num_views": len(per_view),
        "mean": mean,
        "per_view": per_view,
        "num_primitives": model.num_primitives,
        "footprint_mb": model.footprint_bytes() / 2**20,
        "render_ms": statistics.median(times),
        "render_ms_mean": sum(times) / len(times),
        "backend": renderer.name,  # what rendered, not "auto"
        "device": str(dev),
        "threads": torch.get_num_threads(),
        "lpips_net": lpips_net if "lpips" in metrics else None,
        "kernel": meta["spec"]["kernel"],
        "primitive": meta["spec"].get("primitive", "volumetric"),
        "color": meta["spec"]["color"],
        "warnings": sorted(set(warnings)),
    }
    metrics_path(run, split).write_text(json.dumps(result, indent=2))
    return result


def metrics_path(run: Path, split: str) -> Path:
    """Where ``run_eval`` writes a split's metrics: metrics.json for test, metrics_train.json for train."""
    return Path(run) / ("metrics.json" if split == "test" else f"metrics_{split}.json")
