"""Whole training iteration benchmark: ms per iteration and where the time goes.

    python benchmarks/train_step.py [--scene ../shared/data/lego] [--budget 50000]
                                    [--warmup 300] [--iters 100] [--threads 2] [--out PATH]
                                    [--device cuda]

Trains the scene from random init with the default settings (Gaussian kernel, SH degree 3,
MCMC) on the ``cpu`` backend, twice: with the fused native ops (SSIM, projection, SH; the
default) and without them (``unfused``: a cpu backend object whose projection, SH colour and
SSIM are the ``torch`` backend's, around the native rasteriser). After ``--warmup`` iterations (the SH degree is forced to 3 and every
primitive of the budget exists), it times ``--iters`` iterations, then profiles 20 more with
torch.profiler and groups self CPU time by op. Each variant runs in its own subprocess.
Writes benchmarks/results/train_step.json and prints a table. The target of issue #3: one
iteration on lego (400x400, 50k splats) <= 100 ms on 2 cores.

``--device cuda`` trains on the GPU instead, once with the ``cuda`` backend (Triton
rasteriser) and once with the ``torch`` backend, both on the same GPU (writes
results/train_step_cuda.json); iterations are timed up to a torch.cuda.synchronize and the
profile groups self device time (CUDA kernels) instead of CPU time.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results" / "train_step.json"
RESULTS_CUDA = Path(__file__).resolve().parent / "results" / "train_step_cuda.json"
DEFAULT_SCENE = ROOT.parent / "shared" / "data" / "lego"

#: self-CPU-time groups of the profile (first match wins)
GROUPS = [
    ("rasterise", ("_Rasterize", "_TritonRasterize", "rasterize_fwd_kernel", "rasterize_bwd_kernel")),
    ("ssim", ("_SSIM", "convolution", "conv2d", "mkldnn")),
    ("projection", ("_Project",)),
    ("sh colour", ("_SHColor",)),
    ("adam", ("adam", "Adam", "addcdiv", "lerp", "sqrt")),
    ("gather/scatter visible", ("index", "nonzero")),
]


def variant_backend(variant: str, device: str = "cpu"):
    """The backend object a variant trains with: ``fused`` is ``--backend cpu``; ``unfused`` the
    same native rasteriser with the torch backend's projection, SH colour and SSIM; ``cuda`` and
    ``torch`` those backends on ``device``."""
    from splatk import backends
    from splatk.backends.torch_backend import TorchBackend

    if variant in ("cuda", "torch"):
        return backends.get(variant, device)
    cpu = backends.get("cpu", "cpu")
    if variant == "fused":
        return cpu

    class NativeRasterTorchOps(type(cpu)):
        project = TorchBackend.project
        sh_colors = TorchBackend.sh_colors
        ssim = TorchBackend.ssim

    return NativeRasterTorchOps("cpu")


def run_variant(args) -> dict:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from splatk.data import load_scene
    from splatk.stages.fit import FitConfig, build_model
    from splatk.train.trainer import TrainConfig, Trainer

    torch.set_num_threads(args.threads)
    on_gpu = args.device == "cuda"
    scene = load_scene(args.scene)
    backend = variant_backend(args.variant, args.device)
    cfg = FitConfig(train=TrainConfig(init="random", budget=args.budget, iters=30_000, backend=backend.name,
                                      device=args.device))
    model = build_model(scene, cfg)
    trainer = Trainer(scene, model, cfg.train, backend=backend)
    trainer.it = 3000  # SH degree 3 from the start, as in the second half of a run

    def sync():
        if on_gpu:
            torch.cuda.synchronize()

    for _ in range(args.warmup):
        trainer.train_step()
    sync()
    t = time.perf_counter()
    for _ in range(args.iters):
        trainer.train_step()
    sync()
    ms = (time.perf_counter() - t) / args.iters * 1e3
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if on_gpu else [])
    with profile(activities=activities) as prof:
        for _ in range(20):
            trainer.train_step()
        sync()
    groups = {name: 0.0 for name, _ in GROUPS}
    groups["other"] = 0.0
    total = 0.0
    for ev in prof.key_averages():
        us = ev.self_device_time_total if on_gpu else ev.self_cpu_time_total
        total += us
        for name, keys in GROUPS:
            if any(k in ev.key for k in keys):
                groups[name] += us
                break
        else:
            groups["other"] += us
    share = {k: round(v / total, 3) for k, v in groups.items()}
    return {"ms_per_iter": round(ms, 1), "num_primitives": model.num_primitives,
            "image": [scene.train[0].width, scene.train[0].height], "profile_share": share}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(DEFAULT_SCENE))
    ap.add_argument("--budget", type=int, default=50_000)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                    help="cuda: train on the GPU with the cuda (Triton) and torch backends")
    ap.add_argument("--out", help=f"default {RESULTS.relative_to(ROOT)} ({RESULTS_CUDA.name} with --device cuda)")
    ap.add_argument("--variant", choices=["fused", "unfused", "cuda", "torch"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.out is None:
        args.out = str(RESULTS_CUDA if args.device == "cuda" else RESULTS)
    if args.variant:
        print(json.dumps(run_variant(args)))
        return
    if not Path(args.scene).is_dir():
        sys.exit(f"{args.scene}: scene folder not found (this benchmark reads ../shared/data/lego)")
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            ap.error("--device cuda: this torch sees no CUDA device")
    rows = {}
    for variant in ("cuda", "torch") if args.device == "cuda" else ("fused", "unfused"):
        cmd = [sys.executable, __file__, "--variant", variant, "--scene", args.scene,
               "--budget", str(args.budget), "--warmup", str(args.warmup), "--iters", str(args.iters),
               "--threads", str(args.threads), "--device", args.device]
        load0 = os.getloadavg()[0]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows[variant] = {**json.loads(out.stdout.strip().splitlines()[-1]),
                         "loadavg_before": round(load0, 2)}
    result = {"scene": args.scene, "budget": args.budget, "threads": args.threads, "device": args.device,
              "warmup": args.warmup, "iters": args.iters, "cpu_count": os.cpu_count(),
              "variants": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    names = [n for n, _ in GROUPS] + ["other"]
    print(f"{'variant':10s} {'ms/iter':>8s} " + " ".join(f"{n[:12]:>12s}" for n in names))
    for variant, r in rows.items():
        print(f"{variant:10s} {r['ms_per_iter']:8.1f} "
              + " ".join(f"{100 * r['profile_share'][n]:11.0f}%" for n in names))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    main()
