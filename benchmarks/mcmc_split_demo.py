"""MCMC split scales on the built-in demo scene, over seeds (what `splatk demo` trains).

    python benchmarks/mcmc_split_demo.py [--seeds 0-7] [--out benchmarks/results/mcmc_split_demo.json]

Fits the demo scene (`splatk demo`'s settings: presets/demo.yaml, Gaussian, 3000 primitives,
1500 iterations, random init, schedules scaled to the run) once per seed with the split copies'
scales kept (DBS, the default) and shrunk (3DGS-MCMC Eq. 9), 1 thread each, and prints the test
PSNR per seed and the mean. The demo's outcome swings by several dB with the seed, which is what
this measures against the rule's effect.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
import yaml

from splatk.data.synthetic import make_demo_scene
from splatk.stages.evaluate import run_eval
from splatk.stages.fit import FitConfig, run_fit, scale_schedules_to_run

PRESET = Path(__file__).resolve().parents[1] / "presets" / "demo.yaml"


def demo_config(seed: int, rule: str) -> FitConfig:
    p = yaml.safe_load(PRESET.read_text())
    cfg = FitConfig(kernel=p["kernel"], sh_degree=p["sh_degree"], threads=1)
    t = cfg.train
    t.budget, t.iters, t.init, t.seed, t.split_scales = p["budget"], p["iters"], p["init"], seed, rule
    scale_schedules_to_run(cfg)  # as `splatk fit` does for a 1500-iteration run
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7", help="first-last")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "mcmc_split_demo.json")
    args = ap.parse_args()
    lo, hi = (int(x) for x in args.seeds.split("-"))
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        scene = make_demo_scene(Path(tmp) / "scene")
        for seed in range(lo, hi + 1):
            row = {"seed": seed}
            for rule in ("keep", "shrink"):
                run = run_fit(scene, Path(tmp) / f"{rule}{seed}", demo_config(seed, rule))
                row[rule] = run_eval(run, metrics=("psnr",))["mean"]["psnr"]
            rows.append(row)
            print(f"seed {seed}: kept {row['keep']:.2f} dB, shrunk {row['shrink']:.2f} dB", flush=True)
    mean = {r: sum(x[r] for x in rows) / len(rows) for r in ("keep", "shrink")}
    print(f"mean over {len(rows)} seeds: kept {mean['keep']:.2f} dB, shrunk {mean['shrink']:.2f} dB")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows, "mean": mean, "preset": str(PRESET.name)}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
