"""What MCMC's one-view check (``relocate_one_view``, decision 0113) costs on a fitted learned
model, drawing every primitive against drawing only those whose opacity can reach the floor.

A primitive counts as one-view only if its largest effective peak (opacity x d(0)) is at least
``FLOOR``; d(0) is at most 1, so a primitive under that opacity never counts and
:func:`splatk.train.view_support.one_view_primitives` skips it. This script times both ways, in
turn and in one process (so a busy machine slows both alike), checks that they find the same
primitives, and prints the share of primitives under the floor.

    python benchmarks/one_view_cost.py RUN... [--repeats 3] [--json OUT.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from splatk import backends
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


@torch.no_grad()
def measure(run: Path, repeats: int) -> dict:
    model, _, scene, _ = load_learned_run(run)
    backend = backends.get("auto", torch.device("cpu"))
    seconds = {"every_primitive": [], "above_floor": []}
    masks = {}
    for _ in range(repeats):
        for name, find in (("every_primitive", _every_primitive), ("above_floor", one_view_primitives)):
            start = time.perf_counter()
            masks[name] = find(model, backend, scene.train)
            seconds[name].append(time.perf_counter() - start)
    best = {name: min(times) for name, times in seconds.items()}
    return {"run": str(run), "primitives": model.num_primitives, "train_views": len(scene.train),
            "share_under_floor": float((model.opacities < FLOOR).float().mean()),
            "one_view_primitives": int(masks["above_floor"].sum()),
            "same_mask": bool(torch.equal(masks["every_primitive"], masks["above_floor"])),
            "seconds_every_primitive": best["every_primitive"], "seconds_above_floor": best["above_floor"],
            "speedup": best["every_primitive"] / best["above_floor"]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--repeats", type=int, default=3, help="timings of each way; the fastest is kept")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results = [measure(run, args.repeats) for run in args.runs]
    print(f"{'run':<44} {'prims':>6} {'views':>5} {'under floor':>11} {'one-view':>8} {'same':>5} "
          f"{'every s':>8} {'above s':>8} {'speedup':>7}")
    for r in results:
        print(f"{r['run'][-44:]:<44} {r['primitives']:>6} {r['train_views']:>5} {r['share_under_floor']:>11.2f} "
              f"{r['one_view_primitives']:>8} {r['same_mask']!s:>5} {r['seconds_every_primitive']:>8.3f} "
              f"{r['seconds_above_floor']:>8.3f} {r['speedup']:>7.2f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"floor": FLOOR, "repeats": args.repeats, "runs": results}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
