"""The built-in demo scene over seeds, with setting variants (what `splatk demo` trains).

    python benchmarks/demo_seeds.py [--seeds 0-7] [--variant NAME=key:value,key:value ...]
        [--jobs 2] [--out benchmarks/results/demo_seeds.json]

Fits the demo scene (`splatk demo`'s settings: presets/demo.yaml, Gaussian, 3000 primitives,
1500 iterations, random init, schedules scaled to the run as `splatk fit` does) once per seed and
variant, 1 thread per run, ``--jobs`` runs at a time, and prints the test and train PSNR per seed
and their mean and minimum per variant. A variant's settings (TrainConfig or FitConfig fields,
and ``short_run_lrs`` as in the preset) are applied after the scaling, so they stay as given.
Without ``--variant``: the defaults only.

The demo's outcome swings by several dB with the seed; this is how a change to the defaults is
judged on it. Examples (benchmarks/README.md):

    --variant default= --variant dbs-noise=noise_lr:5e4          # MCMC noise: scaled vs 30k
    --variant default= --variant short-run-lrs=short_run_lrs:true # `fit --short-run-lrs`
    --variant keep=split_scales:keep,noise_lr:5e4 --variant shrink=split_scales:shrink,noise_lr:5e4
"""
from __future__ import annotations

import argparse
import json
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import yaml

PRESET = Path(__file__).resolve().parents[1] / "presets" / "demo.yaml"


def demo_config(seed: int, overrides: dict):
    """The demo preset's settings for ``seed``, with a variant's ``overrides`` (flat option
    names), resolved as `splatk fit` resolves them (short-run scaling included; an override
    stays as given)."""
    from splatk.stages.fit_config import fit_config_from_options

    options = {**yaml.safe_load(PRESET.read_text()), "threads": 1, "seed": seed, **overrides}
    return fit_config_from_options(options, {k: "variant" for k in overrides})[0]


def fit_one(job: tuple[int, str, dict]) -> dict:
    seed, name, overrides = job
    import torch

    torch.set_num_threads(1)
    from splatk.data.synthetic import make_demo_scene
    from splatk.stages.evaluate import run_eval
    from splatk.stages.fit import run_fit

    with tempfile.TemporaryDirectory() as tmp:
        scene = make_demo_scene(Path(tmp) / "scene")
        run = run_fit(scene, Path(tmp) / "run", demo_config(seed, overrides)).path
        test = run_eval(run, metrics=("psnr",))["mean"]["psnr"]
        train = run_eval(run, metrics=("psnr",), split="train")["mean"]["psnr"]
    return {"variant": name, "seed": seed, "test_psnr": test, "train_psnr": train}


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, body = text.partition("=")
    overrides = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition(":")
        overrides[key.strip()] = parse_value(value.strip())
    return name, overrides


def parse_value(text: str):
    # YAML 1.1 reads 5e4 as a string, so numbers first
    for number in (int, float):
        try:
            return number(text)
        except ValueError:
            pass
    return yaml.safe_load(text)  # true/false, strings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7", help="first-last")
    ap.add_argument("--variant", action="append", default=[], help="NAME=key:value,... (repeat)")
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time (1 thread each)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "demo_seeds.json")
    args = ap.parse_args()
    lo, hi = (int(x) for x in args.seeds.split("-"))
    variants = dict(parse_variant(v) for v in args.variant) or {"default": {}}
    for name, overrides in variants.items():
        demo_config(0, overrides)  # reject a misspelt setting before minutes of training
    jobs = [(seed, name, o) for name, o in variants.items() for seed in range(lo, hi + 1)]
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(fit_one, jobs))
    summary = {}
    print(f"{'variant':<16} {'test mean':>9} {'test min':>8} {'train mean':>10}  test PSNR per seed")
    for name in variants:
        mine = [r for r in rows if r["variant"] == name]
        test = [r["test_psnr"] for r in mine]
        train = [r["train_psnr"] for r in mine]
        summary[name] = {"settings": variants[name], "test_mean": sum(test) / len(test), "test_min": min(test),
                         "train_mean": sum(train) / len(train)}
        s = summary[name]
        print(f"{name:<16} {s['test_mean']:>9.2f} {s['test_min']:>8.2f} {s['train_mean']:>10.2f}  "
              + " ".join(f"{x:.2f}" for x in test))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"preset": PRESET.name, "seeds": [lo, hi], "summary": summary, "rows": rows},
                                   indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
