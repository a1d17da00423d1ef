"""3DGS's adaptive density control against Gaussian-MCMC at ADC's final primitive count: the check
that `--strategy adc` trains as 3DGS does.

    python benchmarks/adc_check.py OUT [--scene lego] [--downscale 4] [--iters 30000]
        [--arms adc,adc-reg,adc-opacity-reg,adc-scale-reg,mcmc] [--device cuda]

Arm ``adc`` is ``splatk fit SCENE --out OUT/runs/adc --strategy adc --iters N --downscale D
--threads 1`` (with ``--device cuda``: on the GPU, cuda backend). Arm ``adc-reg`` is the same
with MCMC's opacity and scale regularisers (``--opacity-reg 0.01 --scale-reg 0.01``, which 3DGS
does not have): where ADC falls behind MCMC, it tells the density control from the regularisers. Arms ``adc-opacity-reg`` and ``adc-scale-reg`` add
one of the two each, to tell which of them closes the gap. Arm ``mcmc`` is the fit with the default
strategy and ``--budget`` set to the ADC run's final primitive count (so it needs the ADC run).
Each is followed by ``splatk eval --metrics psnr,ssim --json`` on the test views and ``--metrics
psnr`` on the train views. A run folder that already has its ``eval.json`` is not run again; one
stopped part-way (a checkpoint, no ``eval.json``) goes on with ``splatk fit --resume``. Prints the
table, the ADC run's primitive count at each logged iteration, its opacity resets and rollbacks,
and writes OUT/adc_check.json (the committed ones: benchmarks/results/adc_check_lego_30k.json and
adc_check_lego_7k.json, 30k and 7k iterations at 1/4 resolution).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
from pathlib import Path

import torch

from splatk.train.trainer import TrainConfig

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


#: each arm's flags beside --budget; adc-reg names the regularisers MCMC runs with (splatk's
#: defaults, which --strategy adc turns off)
ARM_FLAGS = {"adc": ["--strategy", "adc"],
             "adc-reg": ["--strategy", "adc", "--opacity-reg", str(TrainConfig.opacity_reg),
                         "--scale-reg", str(TrainConfig.scale_reg)],
             "adc-opacity-reg": ["--strategy", "adc", "--opacity-reg", str(TrainConfig.opacity_reg)],
             "adc-scale-reg": ["--strategy", "adc", "--scale-reg", str(TrainConfig.scale_reg)]}
ADC_ARMS = tuple(ARM_FLAGS)


def fit_and_eval(scene: Path, run: Path, flags: list[str], args) -> dict:
    """Test-view PSNR and SSIM, and the train views' PSNR, of the run in ``run``."""
    result = run / "eval.json"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if not result.exists():
        if (run / "checkpoints" / "last.pt").exists():
            fit = ["--resume"]  # an arm stopped part-way goes on from its checkpoint
        else:
            fit = [str(scene), "--overwrite", "--iters", str(args.iters), "--downscale", str(args.downscale), *flags,
                   "--device", args.device]
        subprocess.run(["splatk", "fit", *fit, "--out", str(run), "--threads", "1", "-q"], check=True, env=env)
        evaluated = subprocess.run(["splatk", "eval", str(run), "--metrics", "psnr,ssim", "--json",
                                    "--device", args.device], check=True, env=env, capture_output=True, text=True)
        result.write_text(evaluated.stdout)
    train = run / "metrics_train.json"
    if not train.exists():
        subprocess.run(["splatk", "eval", str(run), "--split", "train", "--metrics", "psnr", "--device", args.device],
                       check=True, env=env, capture_output=True)
    mean = json.loads(result.read_text())["mean"]
    return {**mean, "train_psnr": json.loads(train.read_text())["mean"]["psnr"]}


def adc_history(run: Path) -> dict:
    """Primitive count per logged iteration and the trainer's events (from fit.json / the log)."""
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    fit = json.loads((run / "fit.json").read_text())
    return {"count": {r["it"]: r["num"] for r in log if r["it"] % 1000 == 0},
            "final_primitives": fit["num_primitives"],
            "rollbacks": [e for e in fit.get("events", []) if "rollback" in e.get("event", "")],
            "opacity_resets": [e["iteration"] for e in fit.get("events", []) if e.get("event") == "opacity_reset"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--iters", type=int, default=30000)
    ap.add_argument("--device", default="cpu", help="torch device the arms fit and are evaluated on (cpu, cuda)")
    ap.add_argument("--arms", default="adc,mcmc", help=f"comma-separated: {', '.join(ADC_ARMS)}, mcmc")
    args = ap.parse_args()
    scene = Path(args.scene) if Path(args.scene).is_dir() else DATA / args.scene
    runs = args.out / "runs"
    arms = args.arms.split(",")
    unknown = set(arms) - {*ADC_ARMS, "mcmc"}
    if unknown:
        ap.error(f"unknown arm(s) {', '.join(sorted(unknown))}: use {', '.join(ADC_ARMS)}, mcmc")
    rows, history = {}, {}
    # the MCMC arm's budget is the ADC arm's final count, so it needs the ADC run
    for arm in [a for a in ADC_ARMS if a in arms or (a == "adc" and "mcmc" in arms)]:
        rows[f"3dgs-{arm}"] = fit_and_eval(scene, runs / arm, ARM_FLAGS[arm], args)
        history[arm] = adc_history(runs / arm)
    mcmc = None
    if "mcmc" in arms:
        budget = history["adc"]["final_primitives"]
        rows["3dgs-mcmc"] = fit_and_eval(scene, runs / "mcmc", ["--budget", str(budget)], args)
        # MCMC may end below its budget (it holds growth while many primitives are dead)
        mcmc = adc_history(runs / "mcmc")
    print(f"{args.scene}, {args.iters} iterations, 1/{args.downscale:g} resolution")
    print(f"{'method':<20} {'test PSNR':>9} {'SSIM':>7} {'train PSNR':>10} {'primitives':>10}")
    finals = {f"3dgs-{arm}": h["final_primitives"] for arm, h in history.items()}
    if mcmc:
        finals["3dgs-mcmc"] = mcmc["final_primitives"]
    for name, m in rows.items():
        print(f"{name:<20} {m['psnr']:9.2f} {m['ssim']:7.4f} {m['train_psnr']:10.2f} {finals[name]:10,}")
    step = max(1000, round(args.iters / 10, -3))  # the counts are kept at every 1000th iteration
    for arm, h in history.items():
        counts = h["count"]
        print(f"{arm} primitives: " + ", ".join(f"{it}: {n:,}" for it, n in counts.items() if it % step == 0))
        print(f"{arm} rollbacks: {len(h['rollbacks'])}")
        print(f"{arm} opacity resets at: {', '.join(map(str, h['opacity_resets'])) or 'none'}")
    if mcmc:
        print(f"MCMC rollbacks: {len(mcmc['rollbacks'])}")
    out = {"scene": args.scene, "iters": args.iters, "downscale": args.downscale, "results": rows,
           **{arm: history.get(arm) for arm in ADC_ARMS}, "mcmc": mcmc,
           "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
                       "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"}}
    (args.out / "adc_check.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
