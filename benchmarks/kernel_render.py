"""Render time of the learned kernel against the Gaussian on the same trained geometry.

    python benchmarks/kernel_render.py RUN [--views 10] [--reps 7] [--threads 2] [--out PATH]
        [--downscale D]

RUN is a finished `splatk fit` run with the Gaussian kernel (e.g. `splatk fit
../shared/data/lego --out runs/lego --budget 50000 --time-budget 10m`). The learned models
reuse its primitives: same centres, rotations, opacities and colours, scales x3 (the learned
kernel's support ends at 1 sigma, the Gaussian's at 3, so the screen footprints match), and
zero latents. A kernel's time is the median over ``--reps`` passes of the mean time per view
over the first ``--views`` test views, of `model.render` without gradients on the ``cpu``
backend (projection, colour, Phi_proj / Phi_dec for the learned kernel, rasterisation); the
passes are interleaved across the kernels. Writes benchmarks/results/kernel_render.json and
prints a table. Issue #4's target: learned k=2 <= 1.3x the Gaussian.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "kernel_render.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--downscale", type=float, help="render at this downscale (default: the run's)")
    args = ap.parse_args()

    import torch

    from splatk import backends
    from splatk.data import load_scene
    from splatk.kernels import make_kernel
    from splatk.models.io import load_model
    from splatk.models.volumetric import SplatModel

    torch.set_num_threads(args.threads)
    model, meta = load_model(Path(args.run) / "model.pt")
    if model.kernel.name != "gaussian":
        raise SystemExit(f"{args.run}: needs a run with the Gaussian kernel, found {model.kernel.name}")
    ds = args.downscale if args.downscale is not None else meta.get("downscale", 1)
    scene = load_scene(meta["scene"], downscale=ds)
    cams = scene.test[: args.views]
    bg = torch.tensor(scene.background)
    cpu = backends.get("cpu")

    models = {"gaussian": model}
    prims = {k: v.detach().clone() for k, v in model.prims.items()}
    prims["log_scales"] = prims["log_scales"] + math.log(3.0)
    for precision in ("auto", "fp32"):
        for k in (2, 4, 8):
            kernel = make_kernel("learned", k=k, proj_precision=precision)
            p = dict(prims)
            p.update(kernel.init_primitive_params(model.num_primitives, torch.device("cpu")))
            models[f"learned k={k} ({precision})"] = SplatModel(kernel, model.color, p)

    # passes interleaved across the models, so that drift in this VM's speed (10% between
    # minutes is common) hits every model alike; a model's time is the median of its passes
    passes: dict[str, list[float]] = {name: [] for name in models}
    with torch.no_grad():
        for m in models.values():
            for c in cams[:2]:
                m.render(c, bg, backend=cpu)
        for _ in range(args.reps):
            for name, m in models.items():
                t = time.perf_counter()
                for c in cams:
                    m.render(c, bg, backend=cpu)
                passes[name].append((time.perf_counter() - t) / len(cams) * 1e3)
    rows = {name: {"ms": statistics.median(v)} for name, v in passes.items()}
    base = rows["gaussian"]["ms"]
    for r in rows.values():
        r["ms"] = round(r["ms"], 1)
        r["vs_gaussian"] = round(r["ms"] / base, 2)
    result = {"run": str(Path(args.run).resolve()), "num_primitives": model.num_primitives,
              "image": [cams[0].width, cams[0].height], "views": len(cams), "reps": args.reps,
              "threads": args.threads, "loadavg": round(os.getloadavg()[0], 2), "kernels": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'kernel':24s} {'ms/render':>10s} {'x gaussian':>11s}")
    for name, r in rows.items():
        print(f"{name:24s} {r['ms']:10.1f} {r['vs_gaussian']:11.2f}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
