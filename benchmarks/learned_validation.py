"""The learned kernel against the Gaussian on the tuning and validation scenes of decision 0100,
at 7,000 iterations and 1/2 resolution, every other setting default.

    python benchmarks/learned_validation.py OUT [--scenes juicebox_frontal,...] [--kernels gaussian,learned]
        [--iters 7000] [--downscale 2] [--budget 20000] [--jobs 2]

Forward-facing scenes (``*_frontal``) are made under OUT/scenes by
``benchmarks/make_frontal_scene.py`` from the shared 360-degree capture of the same name; the
others are read from ``../shared/data``. Each (scene, kernel) is one ``splatk fit SCENE --out
OUT/runs/SCENE_KERNEL --kernel KERNEL --iters ... --threads 1`` and one ``splatk eval --metrics
psnr --json``; a run folder that already has its ``eval.json`` is not run again, so the grid
resumes. Prints the table and writes OUT/learned_validation.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"
#: decision 0100's split (juicebox_frontal and bonsai_frontal chose values of decision 0101/0102)
TUNING = ("cup", "bonsai_frontal", "juicebox_frontal")
VALIDATION = ("beer_can_frontal", "juicebox", "beer_can")


def scene_path(name: str, out: Path) -> Path:
    if not name.endswith("_frontal"):
        return DATA / name
    made = out / "scenes" / name
    if not made.exists():
        subprocess.run([sys.executable, str(HERE / "make_frontal_scene.py"), str(DATA / name[:-len("_frontal")]),
                        str(made), "--fraction", "0.33"], check=True)
    return made


def run_one(scene: str, kernel: str, args, out: Path) -> dict:
    run = out / "runs" / f"{scene}_{kernel}"
    result = run / "eval.json"
    if not result.exists():
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run(["splatk", "fit", str(scene_path(scene, out)), "--out", str(run), "--overwrite",
                        "--kernel", kernel, "--iters", str(args.iters), "--downscale", str(args.downscale),
                        "--budget", str(args.budget), "--threads", "1", "-q"], check=True, env=env)
        evaluated = subprocess.run(["splatk", "eval", str(run), "--metrics", "psnr", "--json"], check=True,
                                   env=env, capture_output=True, text=True)
        result.write_text(evaluated.stdout)
    fit = json.loads((run / "fit.json").read_text())
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    return {"scene": scene, "kernel": kernel, "set": "tuning" if scene in TUNING else "validation",
            "test_psnr": json.loads(result.read_text())["mean"]["psnr"], "primitives": fit["num_primitives"],
            "rollbacks": sum("rolled back" in (r.get("event") or "") for r in log)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scenes", default=",".join(TUNING + VALIDATION))
    ap.add_argument("--kernels", default="gaussian,learned")
    ap.add_argument("--iters", type=int, default=7000)
    ap.add_argument("--downscale", type=float, default=2)
    ap.add_argument("--budget", type=int, default=20000)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    cells = [(s, k) for s in args.scenes.split(",") for k in args.kernels.split(",")]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda c: run_one(*c, args, args.out), cells))
    kernels = args.kernels.split(",")
    print(f"{'scene':<18} {'set':<10} " + " ".join(f"{k:>10}" for k in kernels) + "   learned - gaussian")
    for scene in args.scenes.split(","):
        got = {r["kernel"]: r for r in rows if r["scene"] == scene}
        gap = (f"{got['learned']['test_psnr'] - got['gaussian']['test_psnr']:+.2f}"
               if {"learned", "gaussian"} <= set(got) else "")
        print(f"{scene:<18} {got[kernels[0]]['set']:<10} "
              + " ".join(f"{got[k]['test_psnr']:>10.2f}" for k in kernels) + f"   {gap}")
    doc = {"iters": args.iters, "downscale": args.downscale, "budget": args.budget, "rows": rows}
    (args.out / "learned_validation.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
