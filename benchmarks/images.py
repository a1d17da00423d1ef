"""Image representation benchmark: the learned kernel against GabSplat and the Gaussian at two budgets.

    python benchmarks/images.py [--downscale 8] [--iters 500] [--budgets 2048,6144] [--seeds 0,1]
                                [--images kodim01,kodim05] [--kernels ...] [--jobs 2] [--out PATH]

The defaults (96x64 photos, 500 iterations, 2 and 6 KiB: the bytes per pixel of 8 and 24 KiB at
192x128) let the grid of six photos, two budgets and four kernels finish within about an hour on a
shared 2-core machine, GabSplat's and the paper kernel's torch path being the slow part.

Fits every photo in ../shared/data/images with every kernel at every budget (`splatk image`'s
stage), one process per fit with torch.set_num_threads(1), up to --jobs at a time. Kernels:

* ``gaussian``: GaussianImage's kernel; ``gabsplat``: the paper's GabSplat baseline (`splatk
  image --kernel gabsplat`); ``gabor``: splatk's two-wave Gabor on the Cholesky frame.
* ``learned-paper``: `splatk image --mode paper --kernel learned`, the paper's planar learned
  kernel (a 10-float latent per splat) with the budget counting the primitives only, as the
  paper's comparison does (its float16 decoder, 370 bytes, is stored but not counted).
* ``learned``: `splatk image --kernel learned` as it ships (tuned mode: a palette of shapes and a
  turn per splat; its float16 decoder and palette, 498 bytes, paid out of the budget).

Prints a table of PSNR / SSIM / LPIPS per (budget, kernel), averaged over the photos, the
per-photo PSNR and each learned mode's margin over GabSplat and the Gaussian; writes every fit's
metrics to --out (default benchmarks/results/images.json) after each fit, and on a rerun with the
same settings keeps the fits already there (delete the file to start over). With several
``--seeds`` every mean is over photos and seeds.
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
KERNELS = ("gaussian", "gabsplat", "learned-paper", "learned")
#: what a job's rows must share with the file's to be reused by a rerun
SETTINGS_KEYS = ("downscale", "iters", "latent_dim")

_CHILD = """
import json, sys, torch
torch.set_num_threads(1)
from pathlib import Path
from splatk.image.bytes import bytes_per_primitive, network_bytes, num_primitives
from splatk.image.fit import ImageFitConfig
from splatk.stages.image_fit import run_image_fit
a = json.loads(sys.argv[1])
kernel, budget, shapes, mode = a["kernel"], a["budget"], ImageFitConfig.shapes, "tuned"
if kernel == "learned-paper":  # the paper's planar kernel and byte count
    kernel, mode = "learned", "paper"
if kernel.startswith("learned-shapes"):  # learned-shapesK: a palette of K shapes (0: a latent per splat)
    kernel, shapes = "learned", int(kernel[len("learned-shapes"):])
if kernel == "learned-samecount":  # the Gaussian's primitive count, so more bytes: the shape's own gain
    kernel, shapes = "learned", 0
    budget = (num_primitives("gaussian", budget) * bytes_per_primitive("learned", a["latent_dim"])
              + network_bytes("learned", a["latent_dim"]))
cfg = ImageFitConfig(kernel=kernel, mode=mode, budget_bytes=budget, iters=a["iters"], seed=a["seed"],
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


def _key(job: dict) -> tuple:
    return (Path(job["photo"]).stem, job["kernel"], job["budget"], job["seed"])


def _load_done(path: Path, a) -> dict:
    """The fits in ``path`` made with the same settings as ``a``, by :func:`_key` (none if the file
    is missing or its settings differ)."""
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    if any(data.get("settings", {}).get(k) != getattr(a, k) for k in SETTINGS_KEYS):
        raise SystemExit(f"{path} holds fits with other settings ({', '.join(SETTINGS_KEYS)}); "
                         "pass another --out or delete it")
    return {_key(r): r for r in data.get("runs", []) if "error" not in r}


def _write(path: Path, a, rows: list, summary: dict, wall: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({
        "settings": {"downscale": a.downscale, "iters": a.iters, "budgets": [int(b) for b in a.budgets.split(",")],
                     "seeds": [int(x) for x in a.seeds.split(",")], "latent_dim": a.latent_dim,
                     "images": sorted({r["photo"] for r in rows}), "kernels": a.kernels.split(","),
                     "jobs": a.jobs, "threads_per_fit": 1, "wall_seconds_this_run": wall,
                     "machine": platform.platform(), "cpu": _cpu_name(),
                     "command": " ".join(["python", "benchmarks/images.py"] + sys.argv[1:])},
        "summary": summary, "runs": rows}, indent=2) + "\n")
    tmp.replace(path)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--budgets", default="2048,6144", help="comma-separated byte budgets")
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
    done = _load_done(a.out, a)
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [{"photo": str(p), "kernel": k, "budget": b, "iters": a.iters, "seed": seed,
                 "downscale": a.downscale, "latent_dim": a.latent_dim,
                 "out": f"{tmp}/{p.stem}_{k}_{b}_{seed}"}
                for seed in seeds for b in budgets for p in photos for k in kernels]
        rows = [done[_key(j)] for j in jobs if _key(j) in done]
        todo = [j for j in jobs if _key(j) not in done]
        print(f"{len(rows)} fits kept from {a.out}, {len(todo)} to run", flush=True)
        with ThreadPoolExecutor(a.jobs) as pool:
            for r in pool.map(fit_one, todo):
                r.pop("out", None)
                rows.append(r)
                tag = "ERROR" if "error" in r else f"{r['psnr']:.2f} dB {r['seconds']:.0f} s"
                print(f"  {Path(r['photo']).stem} {r['kernel']:16s} {r['budget']:6d} B seed {r['seed']}: {tag}",
                      flush=True)
                if "error" not in r:
                    _write(a.out, a, rows, {}, time.time() - t0)
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
                 "bytes": sel[0].get("counted_bytes", sel[0]["bytes"]), "file_bytes": sel[0]["bytes"],
                 "num_primitives": sel[0]["num_primitives"], "n": len(sel)}
            summary[f"{b}/{k}"] = s
            print(f"{b:7d} {k:16} {s['num_primitives']:6d} {s['psnr']:6.2f} {s['ssim']:6.3f} "
                  f"{s['lpips']:6.3f} {s['seconds']:6.0f}")
        g, gab = summary.get(f"{b}/gaussian"), summary.get(f"{b}/gabsplat")
        for k in ("learned-paper", "learned"):
            lr = summary.get(f"{b}/{k}")
            if lr and (g or gab):
                print(f"{'':7} {k} - " + ", ".join(f"{name} {lr['psnr'] - ref['psnr']:+.2f} dB" for name, ref
                                                   in (("gabsplat", gab), ("gaussian", g)) if ref))
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
    _write(a.out, a, [r for r in rows if "error" not in r], summary, wall)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
