"""The learned kernel against the Gaussian on the tuning and validation scenes of decision 0100,
every other setting default, under one of two protocols:

* ``7k``: 7,000 iterations at 1/2 resolution, 20k primitives, SH degree 3;
* ``30k``: the paper's equal-memory protocol, 30,000 iterations (no short-run scaling) at 1/4
  resolution, view-dependent colour off (``--sh-degree 0``) and 1 MB for each kernel
  (``--budget-bytes 1MB``: the primitive count follows from each kernel's bytes).

    python benchmarks/learned_validation.py OUT [--protocol 7k|30k] [--scenes juicebox_frontal,...]
        [--kernels gaussian,learned,learned-k2] [--seed 0] [--jobs 2] [--table-only]
        [--device cuda] [--data DIR]
    python benchmarks/learned_validation.py OUT --protocol 30k --over-seeds [--scenes ...] [--kernels ...]
        [--baseline gaussian]

Kernel ``learned`` is the learned kernel with every default (k chosen by ``--k auto``, decision
0105), ``learned-k2`` / ``-k4`` / ``-k8`` with that k, ``learned-turn`` with every default and decision
0108's turn penalty in training (``benchmarks/learned_turn_penalty.py``, a candidate for the 30k
protocol), ``learned-turn-gap`` with that penalty turning by the scene's train-view gap and only
where the gap is at least 5 degrees (decision 0116), ``learned-z1`` with every default and
networks pretrained for a 1-float latent z3D (``splatk pretrain --latent-dim 1``, made once under
OUT/weights; decision 0115).

Forward-facing scenes (``*_frontal``, ``juicebox_arc2``: ``MADE_SCENES``) are made under OUT/scenes
by ``benchmarks/make_frontal_scene.py`` from a shared 360-degree capture; the others are read from
``../shared/data``. Each (scene, kernel) is one ``splatk fit SCENE --out
OUT/runs/PROTOCOL/SCENE_KERNEL --kernel KERNEL ... --threads 1`` and one ``splatk eval --metrics
psnr --json``; a run folder that already has its ``eval.json`` is not run again, and one whose fit
stopped part-way (it has a checkpoint but no ``eval.json``) goes on with ``splatk fit --resume``, so
the grid resumes. Each run's train views are measured too (``splatk eval --split train``, which writes the
run's ``metrics_train.json``): a kernel that loses on both splits lacks capacity at that budget, one that
loses on the test views only generalises worse. Prints the tables and writes
OUT/learned_validation[_30k][_seedN].json (runs of a seed other than 0 under
OUT/runs/PROTOCOL_seedN/); the rows of scenes and kernels not run this time stay in that file, so a
grid run in parts ends with every part in it. ``--device cuda`` fits on the GPU (the cuda backend; a GPU draws other
random numbers than the CPU, so a seed's cell differs between them) and measures there too (the
torch backend, which renders what the cpu backend does). ``--data`` points at the shared scenes
where they are not at ``../shared/data``.

``--over-seeds`` fits nothing: for every seed whose runs are under OUT/runs/ or whose result file
is in OUT it pairs each learned cell (its run folder, else its row in the result file) with the
``--baseline`` cell (the Gaussian unless told; the k a candidate would replace, such as
``learned``, the default that took k = 2 in every 7k run) of the same scene and seed, and prints
per scene the seeds, each kernel's mean and the mean difference with its standard error over the
seeds (the spread of the differences over sqrt(seeds)); then the average
of the scenes' mean differences per set. Writes OUT/learned_validation[_30k]_over_seeds.json
(``_over_seeds_vs_BASELINE.json`` for another baseline) and a chart of every seed's difference
beside the means (the same name, .png and .svg). ``OUT = benchmarks/results`` tabulates
the committed result files.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

from splatk.bench.charts import draw_seed_gaps

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"
#: decision 0100's split (juicebox_frontal and bonsai_frontal chose values of decision 0101/0102,
#: beer_can_frontal of decision 0108, which made juicebox_arc2 to validate on)
TUNING = ("cup", "bonsai_frontal", "juicebox_frontal", "beer_can_frontal")
VALIDATION = ("juicebox_arc2", "juicebox", "beer_can", "kangaroo")
#: forward-facing scenes made from a shared 360-degree capture: name -> (capture, --start of the
#: reference arc); juicebox_arc2 shares none of its views with juicebox_frontal
MADE_SCENES = {"juicebox_frontal": ("juicebox", 0), "bonsai_frontal": ("bonsai", 0),
               "beer_can_frontal": ("beer_can", 0), "juicebox_arc2": ("juicebox", 32)}
#: each protocol's fit options
PROTOCOLS = {
    "7k": ["--iters", "7000", "--downscale", "2", "--budget", "20000"],
    "30k": ["--iters", "30000", "--downscale", "4", "--sh-degree", "0", "--budget-bytes", "1MB"],
}
#: the bench's kernel names and their fit options
KERNELS = {
    "gaussian": ["--kernel", "gaussian"],
    "learned": ["--kernel", "learned"],  # every default: k auto (decision 0105)
    "learned-k2": ["--kernel", "learned", "--k", "2"],
    "learned-k4": ["--kernel", "learned", "--k", "4"],
    "learned-k8": ["--kernel", "learned", "--k", "8"],
    "learned-turn": ["--kernel", "learned"],  # with decision 0108's turn penalty (learned_turn_penalty.py)
    "learned-turn-gap": ["--kernel", "learned"],  # the turn penalty by the train-view gap (decision 0116)
    "learned-z1": ["--kernel", "learned"],  # with networks pretrained for a 1-float latent (decision 0115)
}
#: kernels whose networks are pretrained for the grid: ``splatk pretrain`` options, the weights going
#: to OUT/weights/KERNEL.pt (made once, then read by every run of that kernel)
PRETRAIN_OPTIONS = {"learned-z1": ["--latent-dim", "1"]}
#: kernels fitted by another command than `splatk fit` (it takes the same arguments)
FIT_COMMANDS = {"learned-turn": [sys.executable, str(HERE / "learned_turn_penalty.py")],
                "learned-turn-gap": [sys.executable, str(HERE / "learned_turn_penalty.py"),
                                     "--degrees", "gap", "--from-gap", "5"]}


def set_of(scene: str) -> str:
    return "tuning" if scene in TUNING else "validation"


def scene_path(name: str, out: Path, data: Path = DATA) -> Path:
    if name not in MADE_SCENES:
        return data / name
    made = out / "scenes" / name
    if not made.exists():
        capture, start = MADE_SCENES[name]
        subprocess.run([sys.executable, str(HERE / "make_frontal_scene.py"), str(data / capture), str(made),
                        "--fraction", "0.33", "--start", str(start)], check=True)
    return made


def pretrained_weights(kernel: str, out: Path) -> list[str]:
    """``--kernel-weights FILE`` for a kernel of ``PRETRAIN_OPTIONS`` (pretrained here the first
    time), nothing for the others."""
    if kernel not in PRETRAIN_OPTIONS:
        return []
    weights = out / "weights" / f"{kernel}.pt"
    if not weights.exists():
        weights.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["splatk", "pretrain", "-o", str(weights), *PRETRAIN_OPTIONS[kernel], "-q"], check=True,
                       env=dict(os.environ, OMP_NUM_THREADS="1"))
    return ["--kernel-weights", str(weights)]


def run_one(scene: str, kernel: str, protocol: str, seed: int, out: Path, table_only: bool = False,
            device: str = "cpu", data: Path = DATA) -> dict | None:
    run = out / "runs" / (protocol if seed == 0 else f"{protocol}_seed{seed}") / f"{scene}_{kernel}"
    result = run / "eval.json"
    if not result.exists():
        if table_only:
            return None
        env = dict(os.environ, OMP_NUM_THREADS="1")
        if (run / "checkpoints" / "last.pt").exists():
            # a cell stopped part-way (SIGTERM, the end of a working day) goes on from its checkpoint
            fit = ["--resume"]
        else:
            fit = [str(scene_path(scene, out, data)), "--overwrite", *KERNELS[kernel], *PROTOCOLS[protocol],
                   "--seed", str(seed), *pretrained_weights(kernel, out)]
        subprocess.run([*FIT_COMMANDS.get(kernel, ["splatk", "fit"]), *fit, "--out", str(run), "--threads", "1",
                        "--device", device, "-q"], check=True, env=env)
        evaluated = subprocess.run(["splatk", "eval", str(run), "--metrics", "psnr", "--json", "--device", device],
                                   check=True, env=env, capture_output=True, text=True)
        result.write_text(evaluated.stdout)
    train = run / "metrics_train.json"
    if not train.exists():  # seconds, not a fit: --table-only measures it too
        subprocess.run(["splatk", "eval", str(run), "--split", "train", "--metrics", "psnr", "--device", device],
                       check=True, env=dict(os.environ, OMP_NUM_THREADS="1"), capture_output=True)
    fit = json.loads((run / "fit.json").read_text())
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    # the k the run used: --k auto writes the k it chose into the kernel options; a run made before
    # decision 0105 without --k has none and took k = 2
    settings = yaml.safe_load((run / "config.yaml").read_text())["settings"]
    k = settings["kernel_options"].get("k", 2)
    return {"scene": scene, "kernel": kernel, "set": set_of(scene),
            "device": settings["device"],
            "cpu": (fit.get("machine") or {}).get("cpu"),  # None for a run made before fit.json named it
            "test_psnr": json.loads(result.read_text())["mean"]["psnr"],
            "train_psnr": json.loads(train.read_text())["mean"]["psnr"], "primitives": fit["num_primitives"],
            "k": k if kernel.startswith("learned") else None,
            "rollbacks": sum("rolled back" in (r.get("event") or "") for r in log)}


def print_table(rows: list[dict], scenes: list[str], kernels: list[str], key: str) -> None:
    """One line per scene: each kernel's ``key`` and each learned kernel's lead over the Gaussian."""
    learned = [k for k in kernels if k != "gaussian"]
    print(f"{'scene':<18} {'set':<10} " + " ".join(f"{k:>13}" for k in kernels)
          + "".join(f"  {k + ' - gaussian':>24}" for k in learned if "gaussian" in kernels))
    for scene in scenes:
        got = {r["kernel"]: r for r in rows if r["scene"] == scene}
        if not got:
            continue
        gaps = "".join(f"  {got[k][key] - got['gaussian'][key]:>+24.2f}" if k in got and "gaussian" in got
                       else f"  {'-':>24}" for k in learned if "gaussian" in kernels)
        print(f"{scene:<18} {set_of(scene):<10} "
              + " ".join(f"{got[k][key]:>13.2f}" if k in got else f"{'-':>13}" for k in kernels) + gaps)


def file_stem(protocol: str) -> str:
    """learned_validation[_30k]: the start of every file name the protocol's grid writes."""
    return "learned_validation" + ("" if protocol == "7k" else f"_{protocol}")


def result_file(out: Path, protocol: str, seed: int) -> Path:
    """OUT/learned_validation[_30k][_seedN].json: the rows of one protocol and seed."""
    return out / (file_stem(protocol) + ("" if seed == 0 else f"_seed{seed}") + ".json")


def saved_rows(out: Path, protocol: str, seed: int) -> dict[tuple[str, str], dict]:
    """The rows of the seed's result file by (scene, kernel); {} without one."""
    path = result_file(out, protocol, seed)
    if not path.is_file():
        return {}
    return {(r["scene"], r["kernel"]): r for r in json.loads(path.read_text())["rows"]}


def merge_rows(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` with each (scene, kernel) that ``new`` has replaced, and ``new``'s others added: a
    grid run in parts (one scene at a time) keeps every part in its result file."""
    fresh = {(r["scene"], r["kernel"]) for r in new}
    return [r for r in old if (r["scene"], r["kernel"]) not in fresh] + new


def seeds_run(out: Path, protocol: str) -> list[int]:
    """The seeds that have a run folder for ``protocol`` under OUT/runs/ or a result file in OUT."""
    found = set()
    for folder in sorted((out / "runs").glob(f"{protocol}*")):
        match = re.fullmatch(re.escape(protocol) + r"(?:_seed(\d+))?", folder.name)
        if match:
            found.add(int(match.group(1) or 0))
    for path in out.glob(f"{file_stem(protocol)}*.json"):
        match = re.fullmatch(re.escape(file_stem(protocol)) + r"(?:_seed(\d+))?\.json", path.name)
        if match:
            found.add(int(match.group(1) or 0))
    return sorted(found)


def over_seeds(out: Path, protocol: str, scenes: list[str], kernels: list[str], baseline: str = "gaussian") -> dict:
    """Each other kernel against ``baseline`` (the Gaussian, or the learned k a candidate would
    replace) of the same scene and seed, over every seed run."""
    others = [k for k in kernels if k != baseline]
    seeds = seeds_run(out, protocol)
    saved = {seed: saved_rows(out, protocol, seed) for seed in seeds}
    per_scene = []
    for scene in scenes:
        for kernel in others:
            pairs = []
            for seed in seeds:
                # a run folder where there is one, else the row its grid saved
                base = (run_one(scene, baseline, protocol, seed, out, table_only=True)
                        or saved[seed].get((scene, baseline)))
                other = run_one(scene, kernel, protocol, seed, out, table_only=True) or saved[seed].get((scene, kernel))
                if base and other:
                    pairs.append((seed, base["test_psnr"], other["test_psnr"]))
            if not pairs:
                continue
            gaps = [o - g for _, g, o in pairs]
            per_scene.append({
                "scene": scene, "kernel": kernel, "set": set_of(scene),
                "seeds": [s for s, _, _ in pairs], "baseline_mean": statistics.mean(g for _, g, _ in pairs),
                "kernel_mean": statistics.mean(o for _, _, o in pairs), "gaps": gaps,
                "gap_mean": statistics.mean(gaps),
                # None for one seed: no spread to measure
                "gap_standard_error": statistics.stdev(gaps) / len(gaps) ** 0.5 if len(gaps) > 1 else None})
    averages = []
    for kernel in others:
        for name in ("tuning", "validation"):
            rows = [r for r in per_scene if r["kernel"] == kernel and r["set"] == name]
            if rows:
                averages.append({"kernel": kernel, "set": name, "scenes": len(rows),
                                 "gap_mean": statistics.mean(r["gap_mean"] for r in rows),
                                 "scenes_below_baseline": sum(r["gap_mean"] < 0 for r in rows)})
    return {"protocol": protocol, "baseline": baseline, "seeds_found": seeds, "per_scene": per_scene,
            "averages": averages}


def print_over_seeds(doc: dict) -> None:
    print(f"{'scene':<18} {'set':<10} {'kernel':<11} {'seeds':>7} {doc['baseline']:>11} {'kernel':>9} "
          f"{'difference':>11} {'+/- s.e.':>9}")
    for r in doc["per_scene"]:
        error = "-" if r["gap_standard_error"] is None else f"{r['gap_standard_error']:.2f}"
        print(f"{r['scene']:<18} {r['set']:<10} {r['kernel']:<11} {len(r['seeds']):>7} {r['baseline_mean']:>11.2f} "
              f"{r['kernel_mean']:>9.2f} {r['gap_mean']:>+11.2f} {error:>9}")
    for a in doc["averages"]:
        print(f"{a['kernel']} on the {a['set']} scenes: {a['gap_mean']:+.2f} dB on average over {a['scenes']} "
              f"scenes' seed means, below {doc['baseline']} on {a['scenes_below_baseline']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--protocol", choices=sorted(PROTOCOLS), default="7k")
    ap.add_argument("--scenes", default=",".join(TUNING + VALIDATION))
    ap.add_argument("--kernels", default="gaussian,learned",
                    help=f"comma-separated, of {', '.join(KERNELS)}")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--table-only", action="store_true",
                    help="fit nothing: tabulate the cells that have run (the others are left out)")
    ap.add_argument("--device", default="cpu", help="torch device to fit on: cpu or cuda")
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the shared scenes")
    ap.add_argument("--over-seeds", action="store_true",
                    help="fit nothing: each scene's mean difference to --baseline over every seed run")
    ap.add_argument("--baseline", default="gaussian",
                    help="with --over-seeds: the kernel the others are measured against")
    args = ap.parse_args()
    kernels, scenes = args.kernels.split(","), args.scenes.split(",")
    unknown = sorted(set(kernels) - set(KERNELS))
    if unknown:
        ap.error(f"unknown kernel(s) {', '.join(unknown)}; choose from {', '.join(KERNELS)}")
    if args.over_seeds:
        doc = over_seeds(args.out, args.protocol, scenes, kernels, args.baseline)
        print_over_seeds(doc)
        against = "" if args.baseline == "gaussian" else f"_vs_{args.baseline}"
        stem = args.out / f"{file_stem(args.protocol)}_over_seeds{against}"
        args.out.mkdir(parents=True, exist_ok=True)
        stem.with_suffix(".json").write_text(json.dumps(doc, indent=1))
        for path in draw_seed_gaps(doc, stem):
            print(f"wrote {path}")
        return
    cells = [(s, k) for s in scenes for k in kernels]
    if not args.table_only:
        for scene in scenes:  # made once here: parallel cells of one scene would each make it
            scene_path(scene, args.out, args.data)
        for kernel in kernels:  # and so are the pretrained networks
            pretrained_weights(kernel, args.out)
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = [r for r in pool.map(lambda c: run_one(*c, args.protocol, args.seed, args.out, args.table_only,
                                                    args.device, args.data), cells)
                if r is not None]
    for split in ("test", "train"):
        print(f"\n{split} PSNR (dB)")
        print_table(rows, scenes, kernels, f"{split}_psnr")
    path = result_file(args.out, args.protocol, args.seed)
    old = list(saved_rows(args.out, args.protocol, args.seed).values())
    doc = {"protocol": args.protocol, "fit_options": PROTOCOLS[args.protocol], "seed": args.seed,
           "rows": merge_rows(old, rows)}
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
