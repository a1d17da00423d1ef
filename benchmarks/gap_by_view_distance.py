"""The learned kernel's lead over the Gaussian per test view, against how far that view is from the
nearest train view, over the runs of ``learned_validation.py``.

    python benchmarks/gap_by_view_distance.py OUT [--protocol 30k] [--kernel learned] [--near-deg 5]
        [--json OUT.json]

For every scene and seed that has both ``OUT/runs/PROTOCOL[_seedN]/SCENE_gaussian`` and
``SCENE_KERNEL`` with their ``eval.json``, each test view's PSNR difference (KERNEL - Gaussian)
beside the angle between its viewing direction and that of the train camera whose centre is
nearest. Prints the views and the mean and median difference of the views nearer than
``--near-deg`` and of the others; ``--json`` writes every figure.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import statistics
import sys
from pathlib import Path

import torch

from splatk.data import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling script, also when imported
from learned_validation import PROTOCOLS, scene_path  # noqa: E402

#: each protocol's image downscale, as its fits ran
DOWNSCALE = {name: float(opts[opts.index("--downscale") + 1]) for name, opts in PROTOCOLS.items()}


def camera_pose(cam) -> tuple[torch.Tensor, torch.Tensor]:
    """(centre, viewing direction) in world space."""
    rot, t = cam.world_to_cam[:3, :3], cam.world_to_cam[:3, 3]
    return -rot.T @ t, rot[2]


def view_angles(scene) -> dict[str, float]:
    """Each test view's angle (degrees) to the train camera whose centre is nearest."""
    train = [camera_pose(c) for c in scene.train]
    centres = torch.stack([c for c, _ in train])
    angles = {}
    for cam in scene.test:
        centre, direction = camera_pose(cam)
        nearest = int((centres - centre).norm(dim=1).argmin())
        cosine = float((train[nearest][1] @ direction).clamp(-1.0, 1.0))
        angles[cam.name] = math.degrees(math.acos(cosine))
    return angles


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="learned_validation.py's OUT folder")
    ap.add_argument("--protocol", choices=sorted(DOWNSCALE), default="30k")
    ap.add_argument("--kernel", default="learned", help="the run name's kernel part, e.g. learned-k2")
    ap.add_argument("--near-deg", type=float, default=5.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    seeds = sorted(p for p in (args.out / "runs").glob(f"{args.protocol}*")
                   if re.fullmatch(rf"{args.protocol}(_seed\d+)?", p.name))
    scenes = sorted({p.name[:-len("_gaussian")] for s in seeds for p in s.glob("*_gaussian")})
    for scene in scenes:
        loaded = load_scene(scene_path(scene, args.out), downscale=DOWNSCALE[args.protocol], test_every=8,
                            eval_split="held-out")
        angles = view_angles(loaded)
        for seed in seeds:
            pair = [seed / f"{scene}_{k}" / "eval.json" for k in ("gaussian", args.kernel)]
            if not all(p.exists() for p in pair):
                continue
            gaussian, other = (json.loads(p.read_text())["per_view"] for p in pair)
            for g, o in zip(gaussian, other):
                rows.append({"scene": scene, "runs": seed.name, "view": g["view"], "angle_deg": angles[g["view"]],
                             "gaussian_psnr": g["psnr"], "kernel_psnr": o["psnr"], "difference": o["psnr"] - g["psnr"]})
    print(f"{'scene':<18} {'runs':<11} {'view':<36} {'deg':>5} {'gaussian':>9} {args.kernel:>9} {'diff':>7}")
    for r in rows:
        print(f"{r['scene']:<18} {r['runs']:<11} {r['view'][-36:]:<36} {r['angle_deg']:>5.1f} "
              f"{r['gaussian_psnr']:>9.2f} {r['kernel_psnr']:>9.2f} {r['difference']:>+7.2f}")
    bands = {}
    for name, keep in ((f"under {args.near_deg:g} deg", lambda a: a < args.near_deg),
                       (f"{args.near_deg:g} deg or more", lambda a: a >= args.near_deg)):
        diffs = [r["difference"] for r in rows if keep(r["angle_deg"])]
        if diffs:
            bands[name] = {"views": len(diffs), "mean": statistics.mean(diffs), "median": statistics.median(diffs)}
            print(f"views {name} from a train view: {len(diffs)}, {args.kernel} - gaussian "
                  f"mean {bands[name]['mean']:+.2f} dB, median {bands[name]['median']:+.2f} dB")
    if args.json:
        args.json.write_text(json.dumps({"protocol": args.protocol, "kernel": args.kernel, "near_deg": args.near_deg,
                                         "bands": bands, "views": rows}, indent=1))


if __name__ == "__main__":
    main()
