"""2DGS's geometry terms on planar fits (decision 0103): test PSNR and the two terms, unweighted,
on the test views, without them, with normal consistency, and with both.

    python benchmarks/planar_geometry_terms.py OUT [--scene cup] [--iters 1000] [--downscale 8]
        [--budget 5000] [--normal-weight 0.05] [--distortion-weight 100]

Each variant is one ``splatk fit SCENE --out OUT/runs/VARIANT --primitive planar --iters ...
--threads 1 [--normal-weight W] [--distortion-weight W]`` and one ``splatk eval --metrics
psnr,ssim --json``; a run folder that already has its ``eval.json`` is not run again. The terms
are measured on the test views with the native backend. Prints the table and writes
OUT/planar_geometry_terms.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
from pathlib import Path

import torch

from splatk import backends
from splatk.data import load_scene
from splatk.functional.surfel_depth import pixel_rays
from splatk.models.io import load_model
from splatk.train.planar_regularisers import depth_distortion, normal_consistency

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def variants(args) -> dict[str, list[str]]:
    normal = ["--normal-weight", str(args.normal_weight)]
    return {"off": [], "normal": normal, "normal+distortion": normal + ["--distortion-weight",
                                                                        str(args.distortion_weight)]}


def fit_and_eval(run: Path, flags: list[str], args) -> dict:
    result = run / "eval.json"
    if not result.exists():
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run(["splatk", "fit", str(DATA / args.scene), "--out", str(run), "--overwrite", "--primitive",
                        "planar", "--iters", str(args.iters), "--downscale", str(args.downscale), "--budget",
                        str(args.budget), "--threads", "1", "-q", *flags], check=True, env=env)
        evaluated = subprocess.run(["splatk", "eval", str(run), "--metrics", "psnr,ssim", "--json"], check=True,
                                   env=env, capture_output=True, text=True)
        result.write_text(evaluated.stdout)
    return json.loads(result.read_text())["mean"]


def test_view_terms(run: Path) -> dict:
    """Mean unweighted normal consistency and depth distortion over the run's test views."""
    model, meta = load_model(run / "model.pt")
    info = meta.get("meta", meta)
    scene = load_scene(info["scene"], downscale=info["downscale"], test_every=info["test_every"],
                       eval_split=info["eval_split"])
    backend, background = backends.get("auto"), torch.tensor(scene.background)
    normal, distortion = [], []
    with torch.no_grad():
        for cam in scene.test:
            out = model.render(cam, background, backend=backend, geometry=True)
            rays = pixel_rays(cam.K, cam.width, cam.height)
            normal.append(float(normal_consistency(out.geometry, out.alpha, rays)))
            distortion.append(float(depth_distortion(out.geometry, out.alpha, rays)))
    return {"normal_loss": sum(normal) / len(normal), "distortion_loss": sum(distortion) / len(distortion)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scene", default="cup")
    ap.add_argument("--iters", type=int, default=1000)
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--budget", type=int, default=5000)
    ap.add_argument("--normal-weight", type=float, default=0.05)
    ap.add_argument("--distortion-weight", type=float, default=100.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = {}
    for name, flags in variants(args).items():
        run = args.out / "runs" / name
        rows[name] = {"flags": flags, **fit_and_eval(run, flags, args), **test_view_terms(run)}
    print(f"{args.scene} 1/{args.downscale}, {args.iters} iterations, {args.budget} surfels (test views)")
    print(f"{'variant':<20} {'PSNR':>7} {'SSIM':>7} {'normal':>8} {'distortion':>11}")
    for name, r in rows.items():
        print(f"{name:<20} {r['psnr']:7.2f} {r['ssim']:7.4f} {r['normal_loss']:8.4f} {r['distortion_loss']:11.3e}")
    doc = {"settings": vars(args) | {"out": str(args.out)}, "machine": platform.processor() or platform.machine(),
           "rows": rows}
    (args.out / "planar_geometry_terms.json").write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
