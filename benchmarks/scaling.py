"""Data-parallel scaling on one machine: 1 process x 2 threads against 2 processes x 1 thread.

    python benchmarks/scaling.py [--scene ../shared/data/lego] [--downscale 4] [--iters 1000]
        [--budget 20000] [--out benchmarks/results/scaling.json]

Fits the scene three ways with the same views seen (iters x 2 views):

- ``1x2``: one process, 2 threads, ``--batch-views 2``;
- ``2x1``: ``--nproc 2``, 1 thread each (gloo on 127.0.0.1), one view per process and step;
- ``1x2_b1``: one process, 2 threads, one view per step for twice the iterations (the paper's
  setting, for reference: it is a different optimiser schedule).

and measures views per second of training (train_seconds in fit.json: rank 0's clock), the
gradient bytes each rank sends into a step's all-reduce, and the test PSNR (`splatk eval`).
A probe then times gloo all-reduces of float32 buffers from 10^4 to 10^7 values between two
processes on this machine (the latency and bandwidth that docs/scaling.md's model takes), and
the model of N machines is printed (``--model JSON`` prints it alone from a result file).

Speed figures depend on the machine's load (the JSON records the load average before and after);
every run uses OMP_WAIT_POLICY=PASSIVE.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
PROBE_SIZES = (10_000, 100_000, 1_000_000, 10_000_000)
PROBE_REPEATS = 20


def splatk(*args) -> list[str]:
    exe = shutil.which("splatk")
    return ([exe] if exe else [sys.executable, "-m", "splatk_cli.main"]) + [str(a) for a in args]


def fit_and_eval(name: str, scene: str, out: Path, args: argparse.Namespace, extra: list[str]) -> dict:
    run = out / name
    cmd = splatk("fit", scene, "--out", run, "--overwrite", "--downscale", args.downscale, "--budget", args.budget,
                 "--seed", args.seed, "--backend", "cpu", "-q", *extra)
    # passive: on a machine shared with other jobs, OpenMP's spinning barriers make 2 threads far
    # slower than 1 whenever the other thread's core is taken (the JSON records the load)
    env = {**os.environ, "OMP_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE"}
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env)
    wall = time.perf_counter() - t0
    subprocess.run(splatk("eval", run, "--metrics", "psnr", "--backend", "cpu"), check=True, env=env,
                   stdout=subprocess.DEVNULL)
    fit = json.loads((run / "fit.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    batch = yaml.safe_load((run / "config.yaml").read_text())["settings"]["train"]["batch_views"]
    views = fit["iterations"] * batch
    return {
        "name": name, "command": " ".join(map(str, cmd)), "iterations": fit["iterations"], "views_seen": views,
        "train_seconds": fit["train_seconds"], "wall_seconds": round(wall, 2),
        "views_per_second": round(views / fit["train_seconds"], 2),
        "num_primitives": fit["num_primitives"], "gradient_bytes_per_step": fit.get("gradient_bytes_per_step", 0),
        "test_psnr": round(metrics["mean"]["psnr"], 3), "loadavg": [round(load0, 2), round(os.getloadavg()[0], 2)],
    }


def _probe_worker(rank: int, port: int, sizes, repeats: int, result_path: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2,
                            timeout=timedelta(seconds=300))
    rows = []
    for n in sizes:
        buf = torch.ones(n)
        dist.all_reduce(buf)  # warm-up: connections, buffers
        dist.barrier()
        t0 = time.perf_counter()
        for _ in range(repeats):
            dist.all_reduce(buf)
        ms = (time.perf_counter() - t0) / repeats * 1e3
        rows.append({"floats": n, "bytes": 4 * n, "ms": round(ms, 3), "GB_per_s": round(4 * n / ms / 1e6, 3)})
    if rank == 0:
        Path(result_path).write_text(json.dumps(rows))
    dist.destroy_process_group()


def allreduce_probe(out: Path) -> list[dict]:
    """Milliseconds per gloo all-reduce of PROBE_SIZES float32 values between two processes."""
    import torch.multiprocessing as mp

    from splatk.train.distributed import free_port

    path = out / "probe.json"
    mp.spawn(_probe_worker, args=(free_port(), PROBE_SIZES, PROBE_REPEATS, str(path)), nprocs=2)
    return json.loads(path.read_text())


#: networks for the model of N machines: (name, bandwidth GB/s, latency per ring hop ms);
#: "loopback" is this machine's probe, the others assumed (10 GbE and 100 Gb/s links, TCP / RDMA)
NETWORKS = (("10 GbE", 1.1, 0.05), ("100 Gb/s", 11.0, 0.01))
#: Adam's update of one primitive's parameters on every rank, ms (benchmarks/results/train_step.json:
#: 4.7 % of 36.1 ms at 50k primitives, 2 threads)
ADAM_MS_PER_PRIMITIVE = 0.047 * 36.1 / 50_000


def allreduce_ms(nbytes: float, n: int, gb_per_s: float, hop_ms: float) -> float:
    """Ring all-reduce of ``nbytes`` over ``n`` ranks: 2 (n - 1) / n of the buffer crosses each
    link, in 2 (n - 1) hops."""
    return 0.0 if n == 1 else 2 * (n - 1) / n * nbytes / (gb_per_s * 1e6) + 2 * (n - 1) * hop_ms


def step_ms(view_ms: float, views_per_step: int, n: int, primitives: int, bytes_per_primitive: float,
            adam_ms_per_primitive: float, gb_per_s: float, hop_ms: float) -> float:
    """One data-parallel step: each rank renders B / n views, updates every primitive, and joins
    the gradients' all-reduce."""
    return (views_per_step / n * view_ms + primitives * adam_ms_per_primitive
            + allreduce_ms(primitives * bytes_per_primitive, n, gb_per_s, hop_ms))


#: views per step of the model's strong scaling
MODEL_BATCH = 16
MODEL_RANKS = (2, 4, 8, 16)


def model(doc: dict) -> None:
    """Print docs/scaling.md's tables from a scaling.json."""
    runs = {r["name"]: r for r in doc["runs"]}
    ddp = runs["2x1"]
    per_prim = ddp["gradient_bytes_per_step"] / ddp["num_primitives"]
    probe = {p["floats"]: p for p in doc["allreduce_probe"]}
    loop_gbs = max(p["GB_per_s"] for p in doc["allreduce_probe"])
    print(f"bytes per primitive {per_prim:.0f}; loopback all-reduce best {loop_gbs:.2f} GB/s; "
          f"smallest buffer {probe[min(probe)]['ms']} ms")
    print("all-reduce ms per step (ring), primitives x network x N:")
    for prims in (20_000, 100_000, 1_000_000, 5_000_000):
        for name, gbs, hop in NETWORKS:
            cells = "  ".join(f"N={n}: {allreduce_ms(prims * per_prim, n, gbs, hop):8.1f}" for n in (2, 8, 32))
            print(f"  {prims:>9,d} {per_prim * prims / 1e6:7.1f} MB  {name:9s} {cells}")
    gpu_view_ms = 53 * 60_000 / 30_000  # the paper's mean training time: 53 min for 30k iterations, RTX 4090
    scenarios = [  # (name, ms per view, primitives, Adam ms per primitive on every rank)
        ("lego 1/4, CPU (the 1x2 run)", 1000 / runs["1x2"]["views_per_second"], ddp["num_primitives"],
         ADAM_MS_PER_PRIMITIVE),
        ("lego 400 px, 50k, CPU (train_step.json)", 36.1, 50_000, ADAM_MS_PER_PRIMITIVE),
        ("1M primitives, GPU (paper's ms/iteration)", gpu_view_ms, 1_000_000, 0.0),
        ("5M primitives, GPU (paper's ms/iteration)", gpu_view_ms, 5_000_000, 0.0),
    ]
    print(f"speed-up (efficiency) over one process, B = {MODEL_BATCH} views per step:")
    for name, view_ms, prims, adam in scenarios:
        for net, gbs, hop in NETWORKS:
            one = step_ms(view_ms, MODEL_BATCH, 1, prims, per_prim, adam, gbs, hop)
            cells = []
            for n in MODEL_RANKS:
                speedup = one / step_ms(view_ms, MODEL_BATCH, n, prims, per_prim, adam, gbs, hop)
                cells.append(f"N={n}: {speedup:4.1f} ({speedup / n:4.0%})")
            print(f"  {name:42s} {view_ms:6.1f} ms/view {net:9s} " + "  ".join(cells))


def main() -> None:
    from splatk.machine import machine_info

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(ROOT.parent / "shared" / "data" / "lego"))
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--iters", type=int, default=1000)
    ap.add_argument("--budget", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", help="Folder for the run folders (default: a temporary one; not kept).")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "scaling.json"))
    ap.add_argument("--model", metavar="JSON", help="Only print the model of N machines from a scaling.json.")
    args = ap.parse_args()
    if args.model:
        model(json.loads(Path(args.model).read_text()))
        return
    runs = Path(args.runs or tempfile.mkdtemp(prefix="splatk-scaling-"))
    runs.mkdir(parents=True, exist_ok=True)
    n = str(args.iters)
    configs = [
        ("1x2", ["--iters", n, "--batch-views", "2", "--threads", "2"]),
        ("2x1", ["--iters", n, "--nproc", "2", "--threads", "1"]),
        ("1x2_b1", ["--iters", str(2 * args.iters), "--batch-views", "1", "--threads", "2"]),
    ]
    rows = []
    for name, extra in configs:
        rows.append(fit_and_eval(name, args.scene, runs, args, extra))
        r = rows[-1]
        print(f"{name:7s} {r['views_per_second']:7.2f} views/s  {r['gradient_bytes_per_step'] / 2**20:7.2f} MiB/step  "
              f"{r['num_primitives']:7,d} prims  test {r['test_psnr']:.2f} dB  load {r['loadavg']}", flush=True)
    probe = allreduce_probe(runs)
    for p in probe:
        print(f"all-reduce {p['bytes'] / 2**20:8.2f} MiB: {p['ms']:8.2f} ms  {p['GB_per_s']:.2f} GB/s")
    doc = {"machine": machine_info(), "date": time.strftime("%Y-%m-%d"), "scene": args.scene,
           "downscale": args.downscale, "budget": args.budget, "runs": rows, "allreduce_probe": probe,
           "loadavg_end": os.getloadavg()}
    Path(args.out).write_text(json.dumps(doc, indent=2))
    print(f"wrote {args.out}")
    model(doc)


if __name__ == "__main__":
    main()
