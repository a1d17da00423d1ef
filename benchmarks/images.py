"""Image representation benchmark: learned vs gaussian vs gabor 2D splats at two byte budgets.

    python benchmarks/images.py [--downscale 4] [--iters 2000] [--budgets 8192,24576] [--seeds 0,1]
                                [--images kodim01,kodim05] [--latent-dim 2] [--jobs 2] [--out PATH]

Fits every photo in ../shared/data/images with every kernel at every budget (`splatk image`'s
stage: float32 bytes of the per-primitive parameters plus, for the learned kernel, its shared
decoder and palette at float16, 498 bytes at latent size 2 and 64 shapes, paid out of the same
budget), one process per fit with
torch.set_num_threads(1), up to --jobs at a time. Prints a table of PSNR / SSIM / LPIPS per
(budget, kernel), averaged over the photos, the per-photo PSNR, and the issue's targets
(learned >= gaussian + 0.5 dB and >= gabor on average); writes every fit's metrics to
benchmarks/results/images.json. With several ``--seeds`` every mean is over photos and seeds.
``learned`` is `splatk image --kernel learned` as it ships (a palette of shapes, see ImageFitConfig).
``learned-shapesK`` fixes the palette at K shapes (``learned-shapes0``: a latent per splat, no
palette). ``--kernels ...,learned-samecount`` adds the learned kernel with a latent per splat at the
Gaussian's primitive count (so with more bytes): what its shape is worth per primitive, before
its latent floats are paid for.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT.parent / "shared" / "data" / "images"
RESULTS = Path(__file__).resolve().parent / "results" / "images.json"
KERNELS = ("gaussian", "gabor", "learned")

_CHILD = """
import json, sys, torch
torch.set_num_threads(1)
from pathlib import Path
from splatk.image.bytes import bytes_per_primitive, network_bytes, num_primitives
from splatk.image.fit import ImageFitConfig
from splatk.stages.image_fit import run_image_fit
a = json.loads(sys.argv[1])
kernel, budget, shapes = a["kernel"], a["budget"], ImageFitConfig.shapes
if kernel.startswith("learned-shapes"):  # learned-shapesK: a palette of K shapes (0: a latent per splat)
    kernel, shapes = "learned", int(kernel[len("learned-shapes"):])
if kernel == "learned-samecount":  # the Gaussian's primitive count, so more bytes: the shape's own gain
    kernel, shapes = "learned", 0
    budget = (num_primitives("gaussian", budget) * bytes_per_primitive("learned", a["latent_dim"])
              + network_bytes("learned", a["latent_dim"]))
cfg = ImageFitConfig(kernel=kernel, budget_bytes=budget, iters=a["iters"], seed=a["seed"],
                     downscale=a["downscale"], latent_dim=a["latent_dim"], shapes=shapes)
p = run_image_fit(Path(a["photo"]), Path(a["out"]), cfg, overwrite=True)
print(p.read_text())
"""


def fit_one(args: dict) -> dict:
    res = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(args)], capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    if res.returncode != 0:
        return {**args, "error": res.stderr[-2000:]}
    m = json.loads(res.stdout)
    m.pop("config", None)
    m.pop("kernel", None)  # keep the job's name (learned-samecount)
    return {**args, **m, "photo": Path(args["photo"]).stem}


def mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--budgets", default="8192,24576", help="comma-separated byte budgets")
    ap.add_argument("--images", default="", help="comma-separated stems (default: all six)")
    ap.add_argument("--kernels", default=",".join(KERNELS))
    ap.add_argument("--seeds", default="0", help="comma-separated seeds; means are over photos and seeds")
    ap.add_argument("--latent-dim", type=int, default=None,
                    help="learned kernel's latent floats per primitive (default: ImageFitConfig's)")
    ap.add_argument("--jobs", type=int, default=1, help="fits run at once (1 thread each)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    a = ap.parse_args()
    if a.latent_dim is None:  # imported here: the parent process needs torch only for this default
        from splatk.image.fit import ImageFitConfig
        a.latent_dim = ImageFitConfig.latent_dim
    photos = sorted(IMAGES.glob("*.png"))
    if a.images:
        want = set(a.images.split(","))
        photos = [p for p in photos if p.stem in want]
    budgets = [int(b) for b in a.budgets.split(",")]
    kernels = a.kernels.split(",")
    seeds = [int(x) for x in a.seeds.split(",")]
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [{"photo": str(p), "kernel": k, "budget": b, "iters": a.iters, "seed": seed,
                 "downscale": a.downscale, "latent_dim": a.latent_dim,
                 "out": f"{tmp}/{p.stem}_{k}_{b}_{seed}"}
                for seed in seeds for b in budgets for p in photos for k in kernels]
        with ThreadPoolExecutor(a.jobs) as pool:
            rows = []
            for r in pool.map(fit_one, jobs):
                r.pop("out", None)
                rows.append(r)
                tag = "ERROR" if "error" in r else f"{r['psnr']:.2f} dB {r['seconds']:.0f} s"
                print(f"  {Path(r['photo']).stem} {r['kernel']:16s} {r['budget']:6d} B seed {r['seed']}: {tag}",
                      flush=True)
    wall = time.time() - t0
    ok = [r for r in rows if "error" not in r]
    print(f"\n{len(photos)} photos, downscale {a.downscale}, {a.iters} iterations, seeds {a.seeds}, "
          f"learned latent {a.latent_dim}, "
          f"wall {wall / 60:.1f} min\n")
    print(f"{'budget':>7} {'kernel':16} {'prims':>6} {'PSNR':>6} {'SSIM':>6} {'LPIPS':>6} {'s/fit':>6}")
    summary = {}
    for b in budgets:
        for k in kernels:
            sel = [r for r in ok if r["budget"] == b and r["kernel"] == k]
            if not sel:
                continue
            s = {"psnr": mean([r["psnr"] for r in sel]), "ssim": mean([r["ssim"] for r in sel]),
                 "lpips": mean([r["lpips"] for r in sel]), "seconds": mean([r["seconds"] for r in sel]),
                 "bytes": sel[0]["bytes"],
                 "num_primitives": sel[0]["num_primitives"], "n": len(sel)}
            summary[f"{b}/{k}"] = s
            print(f"{b:7d} {k:16} {s['num_primitives']:6d} {s['psnr']:6.2f} {s['ssim']:6.3f} "
                  f"{s['lpips']:6.3f} {s['seconds']:6.0f}")
        g, gb, lr = (summary.get(f"{b}/{k}") for k in ("gaussian", "gabor", "learned"))
        if g and gb and lr:
            # the issue's +0.5 dB is "on average", over the photos and the budgets: printed below
            print(f"{'':7} learned - gaussian {lr['psnr'] - g['psnr']:+.2f} dB, "
                  f"learned - gabor {lr['psnr'] - gb['psnr']:+.2f} dB (target >= 0)")
        for k in kernels:
            pal = summary.get(f"{b}/{k}")
            if k.startswith("learned-shapes") and g and pal:
                print(f"{'':7} {k} - gaussian {pal['psnr'] - g['psnr']:+.2f} dB")
        same = summary.get(f"{b}/learned-samecount")
        if g and same:
            print(f"{'':7} learned at the gaussian's count ({same['bytes'] / b:.2f}x the bytes) - gaussian "
                  f"{same['psnr'] - g['psnr']:+.2f} dB")
    gaps = [summary[f"{b}/learned"]["psnr"] - summary[f"{b}/gaussian"]["psnr"] for b in budgets
            if f"{b}/learned" in summary and f"{b}/gaussian" in summary]
    if len(gaps) > 1:  # the "on average": over the photos and the budgets
        print(f"{'':7} over the {len(gaps)} budgets: learned - gaussian {sum(gaps) / len(gaps):+.2f} dB "
              "(target +0.50)")
    print(f"\nper photo PSNR{' (mean over seeds)' if len(seeds) > 1 else ''}:")
    wins = {b: 0 for b in budgets}
    for b in budgets:
        for p in photos:
            cells = {k: mean([r["psnr"] for r in ok if r["budget"] == b and r["photo"] == p.stem
                              and r["kernel"] == k]) for k in kernels}
            print(f"{b:7d} {p.stem:8} " + " ".join(f"{k} {cells[k]:6.2f}" for k in kernels))
            wins[b] += cells.get("learned", float("nan")) > cells.get("gaussian", float("nan"))
    if "learned" in kernels and "gaussian" in kernels:
        print("photos where learned beats gaussian: "
              + ", ".join(f"{wins[b]} of {len(photos)} at {b} B" for b in budgets))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({
        "settings": {"downscale": a.downscale, "iters": a.iters, "budgets": budgets, "seeds": seeds,
                     "latent_dim": a.latent_dim,
                     "images": [p.stem for p in photos], "kernels": kernels, "jobs": a.jobs,
                     "threads_per_fit": 1, "wall_seconds": wall, "machine": platform.platform(),
                     "command": " ".join(["python", "benchmarks/images.py"] + sys.argv[1:])},
        "summary": summary, "runs": rows}, indent=2) + "\n")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
