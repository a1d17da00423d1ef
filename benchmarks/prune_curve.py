"""How many of a finished run's primitives carry its image: prune by contribution, no fine-tuning.

    python benchmarks/prune_curve.py RUN [RUN ...] [--keep 1,0.8,0.6,0.5,0.4,0.3] [--out JSON]

Each primitive's contribution is its blending weight T * alpha summed over every pixel of every
train view (what ``--budget auto``'s final prune uses). For each kept fraction, the primitives
with the largest contributions stay and the rest are dropped; the table gives the mean PSNR on
the train views (what a pruning rule may look at) and on the test views (what it must not). The
question it answers: could ``--budget auto`` prune further than "contributes nothing", guarded by
the train-view PSNR, without costing test PSNR?
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from splatk import backends
from splatk.data import load_scene
from splatk.models.io import load_model
from splatk.stages.autobudget import blending_weights, render_psnr_keeping


def prune_curve(run: Path, fractions: list[float]) -> dict:
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None)
    bg = torch.tensor(scene.background, dtype=torch.float32)
    renderer = backends.get("auto")
    weights = blending_weights(model, scene.train, renderer)
    order = torch.argsort(weights, descending=True)
    share = torch.cumsum(weights[order], 0) / weights.sum().clamp_min(1e-12)
    n, rows = weights.numel(), []
    for frac in fractions:
        k = max(1, int(n * frac))
        rows.append({"keep_fraction": frac, "num_primitives": k, "weight_share": float(share[k - 1]),
                     "train_psnr": render_psnr_keeping(model, order[:k], scene.train, bg, renderer),
                     "test_psnr": render_psnr_keeping(model, order[:k], scene.test, bg, renderer)})
    return {"run": str(run), "scene": meta["scene"], "num_primitives": n, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--keep", default="1,0.8,0.6,0.5,0.4,0.3")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "prune_curve.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    # the full model first: every drop is measured from it
    fractions = sorted({1.0, *(float(x) for x in args.keep.split(","))}, reverse=True)
    curves = []
    print("| run | kept | primitives | weight share | train dB (drop) | test dB (drop) |")
    print("|---|---:|---:|---:|---:|---:|")
    for run in args.runs:
        if not (run / "model.pt").is_file():
            raise SystemExit(f"{run}: no model.pt (a finished `splatk fit` run folder is needed)")
        c = prune_curve(run, fractions)
        curves.append(c)
        base = c["rows"][0]
        for r in c["rows"]:
            print(f"| {run.parents[2].name}/{run.parent.name} | {r['keep_fraction']:.1f} | "
                  f"{r['num_primitives']:,} | {r['weight_share']:.4f} | {r['train_psnr']:.2f} "
                  f"({r['train_psnr'] - base['train_psnr']:+.2f}) | {r['test_psnr']:.2f} "
                  f"({r['test_psnr'] - base['test_psnr']:+.2f}) |", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"keep_fractions": fractions, "curves": curves}, indent=2))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
