"""What the near clip plane changes in runs already fitted: their test PSNR drawn with the near
plane their model file records, and with the scene's (``NEAR_PLANE_OF_EXTENT`` x its extent,
what `splatk fit` now sets; decision 0110).

    python benchmarks/near_plane.py RUN [RUN ...] [--json OUT.json]

For each run (a `splatk fit` folder with its model.pt), renders the test views as `splatk eval`
does (the scene's background, the fastest backend) both ways, and counts the primitives that the
scene's near plane culls in some train view (if there are none, training with it would have been
the same run) and in some test view. Prints a table; ``--json`` writes every figure.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from splatk import backends
from splatk.data import load_scene
from splatk.metrics import psnr
from splatk.models.base import NEAR_PLANE_OF_EXTENT
from splatk.models.io import load_model


@torch.no_grad()
def culled(model, backend, cameras, near_plane: float) -> int:
    """Primitives in some camera's view at a depth at or below ``near_plane``."""
    hit = torch.zeros(model.num_primitives, dtype=torch.bool)
    for cam in cameras:
        proj = backend.project(model.prims["means"], model.prims["quats"], model.scales, cam.world_to_cam, cam.K,
                               cam.width, cam.height, support_sigmas=model.kernel.support_sigmas)
        hit |= proj.visible & (proj.depths <= near_plane)
    return int(hit.sum())


@torch.no_grad()
def test_psnr(model, backend, scene) -> list[float]:
    bg = torch.tensor(scene.background, dtype=torch.float32)
    return [float(psnr(model.render(cam, bg, backend=backend).image.clamp(0, 1), cam.image_float()))
            for cam in scene.test]


def analyse(run: Path) -> dict:
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
    backend = backends.get("auto", torch.device("cpu"))
    recorded, scenes = model.near_plane, NEAR_PLANE_OF_EXTENT * scene.extent
    before = test_psnr(model, backend, scene)
    model.near_plane = scenes
    after = test_psnr(model, backend, scene)
    return {"run": str(run), "kernel": meta["spec"]["kernel"], "scene": Path(meta["scene"]).name,
            "near_plane_recorded": recorded, "near_plane_scene": scenes,
            "culled_in_train_views": culled(model, backend, scene.train, scenes),
            "culled_in_test_views": culled(model, backend, scene.test, scenes),
            "test_psnr_recorded": sum(before) / len(before), "test_psnr_scene": sum(after) / len(after),
            "per_view": [{"view": c.name, "recorded": a, "scene": b} for c, a, b in zip(scene.test, before, after)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [analyse(run) for run in args.runs]
    print(f"{'run':<48} {'kernel':<9} {'near':>12} {'culled train/test':>18} {'test PSNR':>17}")
    for r in rows:
        print(f"{r['run'][-48:]:<48} {r['kernel']:<9} {r['near_plane_recorded']:>5.2f} -> {r['near_plane_scene']:<4.2f} "
              f"{r['culled_in_train_views']:>9} / {r['culled_in_test_views']:<6} "
              f"{r['test_psnr_recorded']:>6.2f} -> {r['test_psnr_scene']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
