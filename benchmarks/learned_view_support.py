"""How many train views draw each learned primitive, and what the test views draw of those that
only one train view draws.

The learned kernel's profile is view-dependent, peak included (decision 0106), so a primitive can
be drawn by one train view and switched off in the others that see it: a floater in front of one
camera that the other cameras' losses never charge for. A Gaussian in that place is drawn by
every view that sees it. Decisions 0110 and 0111 traced kangaroo's near test-view losses at the
30k protocol to such primitives ("view-switched sheets"). This script asks whether they can be
told apart during training.

A primitive is **one-view** as :mod:`splatk.train.view_support` defines it: two or more train
views see it, its second-largest effective peak (opacity x d(0)) over them is under ``--ratio``
(0.25) x its largest, and its largest is at least ``--floor`` (0.1), so that faint primitives do
not count.

Per run and split (train, test) it prints the share of the views' blending weight (sum over
pixels of each primitive's alpha x transmittance) that one-view primitives carry, and the PSNR of
each view drawn as fitted and drawn with the one-view primitives left out (their opacity at 0).
A large test-view share and a test-view gain without them, where the train views lose little,
is the signal a training-time fix could use; the same on scenes where the learned kernel wins is
its cost.

    python benchmarks/learned_view_support.py RUN... [--json OUT.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from splatk import backends
from splatk.metrics import psnr
from splatk.train.view_support import FLOOR, RATIO, effective_peaks, one_view_mask

sys.path.insert(0, str(Path(__file__).resolve().parent))
from learned_donor_view import load_learned_run  # noqa: E402


def blending_weight_share(model, backend, cam, mask: torch.Tensor) -> float:
    """Share of the view's blending weight (sum over pixels of alpha x transmittance) on ``mask``."""
    weights = torch.stack([mask.float(), torch.ones(len(mask))], dim=1)
    with torch.no_grad():
        drawn = model.render(cam, torch.zeros(2), backend=backend, colors=weights).image
    total = float(drawn[..., 1].sum())
    return float(drawn[..., 0].sum()) / total if total > 0 else 0.0


@torch.no_grad()
def psnr_without(model, backend, cam, background, mask: torch.Tensor) -> float:
    logits = model.prims["opacity_logits"]
    kept = logits.detach().clone()
    logits.data[mask] = -30.0  # opacity ~1e-13: under the rasteriser's 1/255 skip
    try:
        image = model.render(cam, background, backend=backend).image.clamp(0, 1)
    finally:
        logits.data.copy_(kept)
    return float(psnr(image, cam.image_float()))


def analyse(run: Path, ratio: float, floor: float) -> dict:
    model, meta, scene, background = load_learned_run(run)
    backend = backends.get("auto", torch.device("cpu"))
    peaks = effective_peaks(model, backend, scene.train)
    seen_by = (~peaks.isnan()).sum(1)
    one_view = one_view_mask(peaks, ratio, floor)
    result = {"run": str(run), "scene": Path(meta["scene"]).name, "primitives": model.num_primitives,
              "one_view_primitives": int(one_view.sum()),
              "seen_by_no_train_view": int((seen_by == 0).sum()), "views": []}
    for split in ("train", "test"):
        for cam in getattr(scene, split):
            with torch.no_grad():
                fitted = model.render(cam, background, backend=backend).image.clamp(0, 1)
            result["views"].append({
                "split": split, "view": cam.name,
                "one_view_weight_share": blending_weight_share(model, backend, cam, one_view),
                "psnr_as_fitted": float(psnr(fitted, cam.image_float())),
                "psnr_without_one_view": psnr_without(model, backend, cam, background, one_view)})
    for split in ("train", "test"):
        rows = [v for v in result["views"] if v["split"] == split]
        result[f"{split}_mean_share"] = sum(v["one_view_weight_share"] for v in rows) / len(rows)
        result[f"{split}_mean_change_db"] = sum(v["psnr_without_one_view"] - v["psnr_as_fitted"]
                                                for v in rows) / len(rows)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--ratio", type=float, default=RATIO)
    parser.add_argument("--floor", type=float, default=FLOOR)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    results = [analyse(run, args.ratio, args.floor) for run in args.runs]
    print(f"{'run':<44} {'prims':>6} {'one-view':>8} {'train share':>11} {'train dB':>8} "
          f"{'test share':>10} {'test dB':>8}   test views: share / change dB")
    for r in results:
        tests = [v for v in r["views"] if v["split"] == "test"]
        per_view = ", ".join(f"{v['view']}: {v['one_view_weight_share']:.3f} / "
                             f"{v['psnr_without_one_view'] - v['psnr_as_fitted']:+.2f}" for v in tests)
        print(f"{r['run'][-44:]:<44} {r['primitives']:>6} {r['one_view_primitives']:>8} "
              f"{r['train_mean_share']:>11.3f} {r['train_mean_change_db']:>+8.2f} "
              f"{r['test_mean_share']:>10.3f} {r['test_mean_change_db']:>+8.2f}   {per_view}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"ratio": args.ratio, "floor": args.floor, "runs": results}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
