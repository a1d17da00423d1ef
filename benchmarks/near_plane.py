"""What a near clip plane at a fraction of the scene's extent would change in runs already fitted
(decision 0110, where it was measured and rejected as a default).

    python benchmarks/near_plane.py RUN [RUN ...] [--fraction 0.04] [--split test|train] [--json OUT.json]

splatk draws every primitive whose centre is more than 0.01 world units in front of the camera
(the projection's floor). For each run (a `splatk fit` folder with its model.pt) this renders the
test (or ``--split train``) views as `splatk eval` does (the scene's background, the fastest backend) as fitted, and
again with the primitives at a camera depth of at most ``fraction`` x the scene's extent
(``Scene.extent``) left out of that view: 0.04 x extent is 3DGS's fixed 0.2 world units on
NeRF-synthetic (lego's extent is 4.89). It also counts the primitives that plane would leave out
of some train view (if none, training with the plane would have been the same run) and of some
test view. Prints a table; ``--json`` writes every figure.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from splatk import backends
from splatk.data import load_scene
from splatk.metrics import psnr
from splatk.models.io import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from near_camera_veils import render_without  # noqa: E402

#: 3DGS's near plane (0.2) over the NeRF-synthetic extent (lego: 4.89)
FRACTION = 0.04


@torch.no_grad()
def nearer_than(model, backend, cam, near_plane: float) -> torch.Tensor:
    """[N] bool: in the view, with the centre at a camera depth of at most ``near_plane``."""
    proj = backend.project(model.prims["means"], model.prims["quats"], model.scales, cam.world_to_cam, cam.K,
                           cam.width, cam.height, support_sigmas=model.kernel.support_sigmas)
    return proj.visible & (proj.depths <= near_plane)


@torch.no_grad()
def view_psnr(model, backend, cam, background, near_plane: float | None) -> float:
    """The view's PSNR as fitted (``near_plane`` None) or with the primitives nearer left out."""
    drop = (torch.zeros(model.num_primitives, dtype=torch.bool) if near_plane is None
            else nearer_than(model, backend, cam, near_plane))
    image = render_without(model, backend, cam, drop, background).image.clamp(0, 1)
    return float(psnr(image, cam.image_float()))


def analyse(run: Path, fraction: float, split: str = "test") -> dict:
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
    backend = backends.get("auto", torch.device("cpu"))
    background = torch.tensor(scene.background, dtype=torch.float32)
    near_plane = fraction * scene.extent
    views = scene.test if split == "test" else scene.train
    fitted = [view_psnr(model, backend, cam, background, None) for cam in views]
    culled = [view_psnr(model, backend, cam, background, near_plane) for cam in views]

    def count(cameras) -> int:
        hit = torch.zeros(model.num_primitives, dtype=torch.bool)
        for cam in cameras:
            hit |= nearer_than(model, backend, cam, near_plane)
        return int(hit.sum())

    return {"run": str(run), "kernel": meta["spec"]["kernel"], "scene": Path(meta["scene"]).name,
            "split": split, "near_plane": near_plane, "culled_in_train_views": count(scene.train),
            "culled_in_test_views": count(scene.test),
            "psnr_fitted": sum(fitted) / len(fitted), "psnr_near_plane": sum(culled) / len(culled),
            "per_view": [{"view": c.name, "fitted": a, "near_plane": b} for c, a, b in zip(views, fitted, culled)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--fraction", type=float, default=FRACTION, help="near plane / scene extent")
    ap.add_argument("--split", choices=["test", "train"], default="test", help="the views to draw")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [analyse(run, args.fraction, args.split) for run in args.runs]
    print(f"{'run':<48} {'kernel':<9} {'near':>5} {'culled train/test':>18} "
          f"{args.split + ' PSNR: fitted, with plane':>31}")
    for r in rows:
        print(f"{r['run'][-48:]:<48} {r['kernel']:<9} {r['near_plane']:>5.2f} "
              f"{r['culled_in_train_views']:>9} / {r['culled_in_test_views']:<6} "
              f"{r['psnr_fitted']:>17.2f} {r['psnr_near_plane']:>12.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
