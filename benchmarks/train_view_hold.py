"""Runs fitted before their model files kept their train cameras, measured with and without decision
0121's hold (Φ_proj reads a primitive's distance as no nearer than the nearest train camera that
draws it).

    python benchmarks/train_view_hold.py RUN [RUN ...] [--json OUT.json] [--split test|train]

Each RUN is a `splatk fit` folder. Its model is measured as `splatk eval --metrics psnr` measures it
twice, from copies in a temporary folder: without train cameras (no hold, as files from before
them), and with the train cameras of its scene (loaded as the run loaded it) written into the file,
as `splatk fit` now writes them. The hold never binds in a train view, so training is unchanged and the difference is
the one a run fitted by the current code shows. Prints each run's mean test PSNR both ways and the
change; ``--json`` writes every view's.
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

from splatk.data import load_scene
from splatk.models.io import load_model, save_model
from splatk.stages.evaluate import run_eval


def model_copy(run: Path, into: Path, with_cameras: bool) -> Path:
    """A copy of ``run``'s model file under ``into``: with its scene's train cameras (loaded as
    the run loaded its scene), or without any (as files from before them)."""
    model, meta = load_model(run / "model.pt")
    model.train_views = None
    cameras = None
    if with_cameras:
        cameras = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0),
                             test_every=meta.get("test_every", 8),
                             background=tuple(meta["background"]) if meta.get("background") else None,
                             eval_split=meta.get("eval_split", "held-out")).train
    spec = meta.pop("spec")
    into.mkdir(parents=True)
    save_model(model, into / "model.pt", spec, meta, cameras)
    return into


def measure(run: Path, split: str = "test") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        before = run_eval(model_copy(run, Path(tmp) / "fitted", False), metrics=("psnr",), split=split)
        after = run_eval(model_copy(run, Path(tmp) / "held", True), metrics=("psnr",), split=split)
    views = [{"view": b["view"], "fitted": b["psnr"], "held": a["psnr"]}
             for b, a in zip(before["per_view"], after["per_view"])]
    return {"run": str(run), "split": split, "fitted": before["mean"]["psnr"], "held": after["mean"]["psnr"],
            "change": after["mean"]["psnr"] - before["mean"]["psnr"], "views": views}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--split", choices=("test", "train"), default="test")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        rows.append(measure(run, args.split))
        print(f"{str(run)[-60:]:<60} {rows[-1]['fitted']:>7.2f} {rows[-1]['held']:>7.2f} {rows[-1]['change']:>+7.3f}",
              flush=True)
        if args.json:  # after each run: a long list can be read while it goes
            args.json.write_text(json.dumps(rows, indent=1))
    if rows:
        print(f"mean change over {len(rows)} runs: {statistics.mean(r['change'] for r in rows):+.3f} dB, "
              f"lowest {min(r['change'] for r in rows):+.3f}")


if __name__ == "__main__":
    main()
