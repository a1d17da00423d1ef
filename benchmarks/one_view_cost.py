"""What MCMC's one-view check (``relocate_one_view``, decision 0113) costs on a fitted learned
model, drawing every primitive against drawing only those whose opacity can reach the floor.

A primitive counts as one-view only if its largest effective peak (opacity x d(0)) is at least
``FLOOR``; d(0) is at most 1, so a primitive under that opacity never counts and
:func:`splatk.train.view_support.one_view_primitives` skips it. This script times both ways, in
turn and in one process (so a busy machine slows both alike), checks that they find the same
primitives, and prints the share of primitives under the floor.

It also times, in the same process, a training iteration's render, loss and backward on each train
view, and gives the check's share of training from the run's own schedule: refine steps x check /
(iterations x iteration + refine steps x check). The optimiser step and MCMC's other work are left
out of the iteration, so the share is an upper bound.

    python benchmarks/one_view_cost.py RUN... [--repeats 3] [--json OUT.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
import yaml

from splatk import backends
from splatk.train.losses import photometric_loss
from splatk.train.mcmc import MCMCConfig, MCMCStrategy
from splatk.train.view_support import (
    FLOOR,
    effective_peaks,
    one_view_mask,
    one_view_primitives,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from learned_donor_view import load_learned_run


def _every_primitive(model, backend, cameras) -> torch.Tensor:
    return one_view_mask(effective_peaks(model, backend, cameras))


def refine_steps(train: dict) -> int:
    """How many refine steps the run's MCMC schedule had (its config.yaml's ``train`` settings)."""
    strategy = MCMCStrategy(MCMCConfig(**train["mcmc"]))
    return sum(strategy.is_refine_step(it, it / train["iters"]) for it in range(1, train["iters"] + 1))


def _iterations(model, backend, scene, background) -> None:
    """A training iteration's render, loss and backward on each train view in turn."""
    for cam in scene.train:
        image = model.render(cam, background, backend=backend).image
        photometric_loss(image, cam.image_float(), backend).backward()
    model.zero_grad(set_to_none=True)


def measure(run: Path, repeats: int) -> dict:
    model, _, scene, background = load_learned_run(run)
    train = yaml.safe_load((run / "config.yaml").read_text())["settings"]["train"]
    backend = backends.get("auto", torch.device("cpu"))
    seconds = {"every_primitive": [], "above_floor": [], "iteration": []}
    masks = {}
    for _ in range(repeats):
        for name, find in (("every_primitive", _every_primitive), ("above_floor", one_view_primitives)):
            start = time.perf_counter()
            with torch.no_grad():
                masks[name] = find(model, backend, scene.train)
            seconds[name].append(time.perf_counter() - start)
        start = time.perf_counter()
        _iterations(model, backend, scene, background)
        seconds["iteration"].append((time.perf_counter() - start) / len(scene.train))
    best = {name: min(times) for name, times in seconds.items()}
    steps = refine_steps(train)
    checks, iterations = steps * best["above_floor"], train["iters"] * best["iteration"]
    return {"run": str(run), "primitives": model.num_primitives, "train_views": len(scene.train),
            "share_under_floor": float((model.opacities < FLOOR).float().mean()),
            "one_view_primitives": int(masks["above_floor"].sum()),
            "same_mask": bool(torch.equal(masks["every_primitive"], masks["above_floor"])),
            "seconds_every_primitive": best["every_primitive"], "seconds_above_floor": best["above_floor"],
            "speedup": best["every_primitive"] / best["above_floor"],
            "seconds_iteration": best["iteration"], "iterations": train["iters"], "refine_steps": steps,
            "share_of_training": checks / (iterations + checks)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--repeats", type=int, default=3, help="timings of each way; the fastest is kept")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results = [measure(run, args.repeats) for run in args.runs]
    print(f"{'run':<44} {'prims':>6} {'views':>5} {'under floor':>11} {'one-view':>8} {'same':>5} "
          f"{'every s':>8} {'above s':>8} {'speedup':>7} {'iter s':>7} {'refines':>7} {'share':>6}")
    for r in results:
        print(f"{r['run'][-44:]:<44} {r['primitives']:>6} {r['train_views']:>5} {r['share_under_floor']:>11.2f} "
              f"{r['one_view_primitives']:>8} {r['same_mask']!s:>5} {r['seconds_every_primitive']:>8.3f} "
              f"{r['seconds_above_floor']:>8.3f} {r['speedup']:>7.2f} {r['seconds_iteration']:>7.3f} "
              f"{r['refine_steps']:>7} {100 * r['share_of_training']:>5.1f}%")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"floor": FLOOR, "repeats": args.repeats, "runs": results}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
