"""3DGS's adaptive density control against Gaussian-MCMC at ADC's final primitive count: the check
that `--strategy adc` trains as 3DGS does.

    python benchmarks/adc_check.py OUT [--scene lego] [--downscale 4] [--iters 30000] [--arms adc,mcmc]

Arm ``adc`` is ``splatk fit SCENE --out OUT/runs/adc --strategy adc --iters N --downscale D
--threads 1``; arm ``mcmc`` is the same with the default strategy and ``--budget`` set to the
ADC run's final primitive count (so it needs the ADC run). Each is followed by ``splatk eval
--metrics psnr,ssim --json``; a run folder that already has its ``eval.json`` is not run again.
Prints the table, the ADC run's primitive count at each logged iteration, its opacity resets and
rollbacks, and writes OUT/adc_check.json (the committed one: benchmarks/results/adc_check_lego.json).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
from pathlib import Path

import torch

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def fit_and_eval(scene: Path, run: Path, flags: list[str], args) -> dict:
    result = run / "eval.json"
    if not result.exists():
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run(["splatk", "fit", str(scene), "--out", str(run), "--overwrite", "--iters", str(args.iters),
                        "--downscale", str(args.downscale), "--threads", "1", "-q", *flags], check=True, env=env)
        evaluated = subprocess.run(["splatk", "eval", str(run), "--metrics", "psnr,ssim", "--json"], check=True,
                                   env=env, capture_output=True, text=True)
        result.write_text(evaluated.stdout)
    return json.loads(result.read_text())["mean"]


def adc_history(run: Path) -> dict:
    """Primitive count per logged iteration and the trainer's events (from fit.json / the log)."""
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    fit = json.loads((run / "fit.json").read_text())
    return {"count": {r["it"]: r["num"] for r in log if r["it"] % 1000 == 0},
            "final_primitives": fit["num_primitives"],
            "rollbacks": [e for e in fit.get("events", []) if "rollback" in e.get("event", "")]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--iters", type=int, default=30000)
    ap.add_argument("--arms", default="adc,mcmc")
    args = ap.parse_args()
    scene = Path(args.scene) if Path(args.scene).is_dir() else DATA / args.scene
    runs = args.out / "runs"
    arms = args.arms.split(",")
    rows, history = {}, None
    if "adc" in arms or "mcmc" in arms:
        rows["3dgs-adc"] = fit_and_eval(scene, runs / "adc", ["--strategy", "adc"], args)
        history = adc_history(runs / "adc")
    mcmc = None
    if "mcmc" in arms:
        rows["3dgs-mcmc"] = fit_and_eval(scene, runs / "mcmc", ["--budget", str(history["final_primitives"])], args)
        # MCMC may end below its budget (it holds growth while many primitives are dead)
        mcmc = adc_history(runs / "mcmc")
    print(f"{args.scene}, {args.iters} iterations, 1/{args.downscale:g} resolution")
    print(f"{'method':<12} {'PSNR':>7} {'SSIM':>7}")
    for name, m in rows.items():
        print(f"{name:<12} {m['psnr']:7.2f} {m['ssim']:7.4f}")
    if history:
        counts = history["count"]
        print("ADC primitives: " + ", ".join(f"{it}: {n:,}" for it, n in counts.items() if it % 3000 == 0))
        print(f"ADC rollbacks: {len(history['rollbacks'])}")
    if mcmc:
        print(f"MCMC primitives at the end: {mcmc['final_primitives']:,} (budget {history['final_primitives']:,}); "
              f"rollbacks: {len(mcmc['rollbacks'])}")
    out = {"scene": args.scene, "iters": args.iters, "downscale": args.downscale, "results": rows,
           "adc": history, "mcmc": mcmc, "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__}}
    (args.out / "adc_check.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
