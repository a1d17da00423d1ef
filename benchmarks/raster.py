"""Rasteriser benchmark: forward and forward+backward time and peak memory per backend.

    python benchmarks/raster.py [--quick] [--threads 2] [--reps 7] [--backends cpu,torch]
                                [--omp-wait-policy passive] [--out PATH] [--device cuda]

Scenes follow ../shared/reference/cpu-peers.md: N splats with centres uniform over the image,
depths U(2, 8), two projected sigmas log-uniform in [0.5, 4] px at width 512 (scaled with the
width), uniformly random rotations, opacities U(0.1, 1), RGB colours; the support is 3 sigma
(mean support radius about 7 px at 512). Table profiles sample the Gaussian exp(-4.5 r^2) at k
radii. Loss: L1 against a random image, as in cpu-peers.

Each configuration runs in its own subprocess (so peak RSS is per configuration, from
getrusage's maxrss): one warm-up forward+backward, then the median of --reps forward passes and
of --reps forward+backward passes, with torch.set_num_threads(--threads). The torch reference
only runs at N = 10k (it takes seconds per render); other torch cells are marked skipped.
Writes benchmarks/results/raster.json and prints a table.

``--device cuda`` renders CUDA tensors and times the ``cuda`` (Triton) backend beside the torch
one on the same GPU (default --backends cuda,torch; writes results/raster_cuda.json): times
wait for the GPU (torch.cuda.synchronize) and the memory column is the peak CUDA memory the
render allocated (torch.cuda.max_memory_allocated), not the process RSS.

Wall times need an otherwise idle machine: when other processes keep the cores busy, each
OpenMP barrier can wait a whole scheduler slice for a descheduled thread, and spinning threads
burn CPU. The JSON therefore also keeps the minimum, the process CPU time per render (all
threads, spinning included) and the load average around each configuration; --threads 1 gives
a contention-robust measure of the work itself (its CPU time). On a shared machine
--omp-wait-policy passive (OMP_WAIT_POLICY for the timed subprocesses) avoids most of that: with
one other busy process, 50k splats at 512x512 took 236 ms with libgomp's default spinning and
64 ms with passive waiting (2 threads), the single-thread time.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results" / "raster.json"
RESULTS_CUDA = Path(__file__).resolve().parent / "results" / "raster_cuda.json"

SIZES = [(512, 512), (1024, 768)]
COUNTS = [10_000, 50_000, 200_000]
PROFILES = [("gaussian", None), ("table", 2), ("table", 8)]
TORCH_MAX_N = 10_000


def make_scene(n: int, width: int, height: int, seed: int = 0):
    import torch

    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 2, generator=g) * torch.tensor([float(width), float(height)])
    log_lo, log_hi = math.log(0.5), math.log(4.0)
    sigmas = torch.exp(torch.rand(n, 2, generator=g) * (log_hi - log_lo) + log_lo) * (width / 512)
    theta = torch.rand(n, generator=g) * math.pi
    c, s = torch.cos(theta), torch.sin(theta)
    i0, i1 = 1 / sigmas[:, 0] ** 2, 1 / sigmas[:, 1] ** 2
    # conic of the 3-sigma support: inv(R diag(sigma^2) R^T) / 9
    conics = torch.stack([c * c * i0 + s * s * i1, c * s * (i0 - i1), s * s * i0 + c * c * i1], -1) / 9
    opacities = torch.rand(n, generator=g) * 0.9 + 0.1
    colors = torch.rand(n, 3, generator=g)
    depths = torch.rand(n, generator=g) * 6 + 2
    radius = 3 * sigmas.max(dim=1).values
    return means, conics, opacities, colors, depths, float(radius.mean())


def profile_for(kind: str, k: int | None, n: int):
    import torch

    from splatk.backends import Profile

    if kind == "gaussian":
        return Profile("gaussian")
    r = torch.linspace(0, 1, k)
    return Profile("table", torch.exp(-4.5 * r * r).expand(n, k).contiguous())


def run_one(cfg: dict) -> dict:
    """Time one configuration in this process (called in a fresh subprocess)."""
    import torch

    from splatk.backends import Profile, rasterize, resolve_backend

    torch.set_num_threads(cfg["threads"])
    device = torch.device(cfg.get("device", "cpu"))
    on_gpu = device.type == "cuda"
    n, width, height = cfg["n"], cfg["width"], cfg["height"]
    means, conics, opac, colors, depths, mean_radius = make_scene(n, width, height)
    depths = depths.to(device)
    prof = profile_for(cfg["kind"], cfg["k"], n)
    leaves = [t.to(device).requires_grad_(True) for t in (means, conics, opac, colors)]
    params = None if prof.params is None else prof.params.to(device).requires_grad_(True)
    target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1)).to(device)
    background = torch.zeros(3, device=device)
    backend = cfg["backend"]
    assert resolve_backend(backend, device) == backend  # an unavailable backend is an error, not a fallback

    def sync():
        if on_gpu:
            torch.cuda.synchronize(device)

    if backend == "cpu":
        assert resolve_backend("cpu") == "cpu"
        from splatk.backends import cpu_native

        ext = cpu_native.load_extension()
    else:
        ext = None

    def forward():
        return rasterize(leaves[0], leaves[1], leaves[2], leaves[3], depths,
                         Profile(prof.kind, params), width, height, background, backend=backend)

    def step():
        out = forward()
        (out.colors - target).abs().mean().backward()

    step()  # warm-up (also builds / loads the extension, compiles the kernels)
    sync()
    if on_gpu:
        torch.cuda.reset_peak_memory_stats(device)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    load_before = os.getloadavg()[0]
    fwd, both, fwd_cpu, both_cpu, phases = [], [], [], [], []
    for _ in range(cfg["reps"]):
        c0, t0 = time.process_time(), time.perf_counter()
        out = forward()
        sync()
        fwd.append(time.perf_counter() - t0)
        fwd_cpu.append(time.process_time() - c0)
        del out
    for _ in range(cfg["reps"]):
        for t in leaves + ([params] if params is not None else []):
            t.grad = None
        c0, t0 = time.process_time(), time.perf_counter()
        step()
        sync()
        both.append(time.perf_counter() - t0)
        both_cpu.append(time.process_time() - c0)
        if ext is not None:
            phases.append(ext.last_timings())
    rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    res = {
        **cfg,
        "fwd_ms": 1e3 * statistics.median(fwd),
        "fwd_bwd_ms": 1e3 * statistics.median(both),
        "fwd_ms_min": 1e3 * min(fwd),
        "fwd_bwd_ms_min": 1e3 * min(both),
        "fwd_cpu_ms": 1e3 * statistics.median(fwd_cpu),
        "fwd_bwd_cpu_ms": 1e3 * statistics.median(both_cpu),
        "loadavg_1min": [load_before, os.getloadavg()[0]],
        "nice": os.nice(0),
        "peak_rss_mb": rss_peak / 1024,
        "rss_growth_after_warmup_mb": (rss_peak - rss_before) / 1024,
        "mean_support_radius_px": mean_radius,
    }
    if on_gpu:
        res["gpu"] = torch.cuda.get_device_name(device)
        res["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    if phases:
        names = ["bbox", "sort", "bin", "raster", "bwd_raster", "bwd_reduce"]
        res["cpu_phases_ms"] = {
            name: 1e3 * statistics.median(p[i] for p in phases) for i, name in enumerate(names)
        }
    return res


def configs(quick: bool, threads: int, reps: int, backends: list[str], device: str = "cpu") -> list[dict]:
    sizes = SIZES[:1] if quick else SIZES
    counts = COUNTS[:2] if quick else COUNTS
    out = []
    for kind, k in PROFILES:
        for width, height in sizes:
            for n in counts:
                for backend in backends:
                    out.append(dict(kind=kind, k=k, n=n, width=width, height=height, device=device,
                                    backend=backend, threads=threads, reps=reps,
                                    skip=backend == "torch" and n > TORCH_MAX_N))
    return out


def machine_info() -> dict:
    import torch

    model = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            model = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": model,
        "logical_cpus": os.cpu_count(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "loadavg_start": os.getloadavg(),
        "threads": None,
    }


def label(r: dict) -> str:
    return r["kind"] if r["k"] is None else f"table k={r['k']}"


def print_table(rows: list[dict]) -> None:
    gpu = any("peak_cuda_mb" in r for r in rows)
    headers = ["profile", "N", "size", "backend", "fwd ms", "fwd+bwd ms", "(min)", "CPU ms",
               "peak CUDA MB" if gpu else "peak RSS MB"]
    lines = []
    for r in rows:
        size = f"{r['width']}x{r['height']}"
        if r.get("skip"):
            cells = ["skipped", "(slow)", "", "", ""]
        elif "error" in r:
            cells = ["error", "", "", "", ""]
        else:
            cells = [f"{r['fwd_ms']:.1f}", f"{r['fwd_bwd_ms']:.1f}", f"{r['fwd_bwd_ms_min']:.1f}",
                     f"{r['fwd_bwd_cpu_ms']:.1f}", f"{r.get('peak_cuda_mb', r['peak_rss_mb']):.0f}"]
        lines.append([label(r), f"{r['n'] // 1000}k", size, r["backend"], *cells])
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title="splatk rasteriser: median ms per render ((min) and process CPU ms "
                            "of fwd+bwd)")
        for h in headers:
            table.add_column(h, justify="right" if h not in ("profile", "backend") else "left")
        for line in lines:
            table.add_row(*line)
        Console().print(table)
    except ImportError:
        widths = [max(len(h), *(len(line[i]) for line in lines)) for i, h in enumerate(headers)]
        print("  ".join(h.ljust(w) for h, w in zip(headers, widths)))
        for line in lines:
            print("  ".join(c.ljust(w) for c, w in zip(line, widths)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="512x512 and N <= 50k only")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=7, help="timed repetitions (median), >= 5")
    ap.add_argument("--backends", help="comma-separated backends to time (default: cpu,torch; "
                                       "cuda,torch with --device cuda)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                    help="where the tensors live (cuda: times the Triton backend beside torch)")
    ap.add_argument("--omp-wait-policy", choices=["passive", "active"],
                    help="OMP_WAIT_POLICY for the timed subprocesses (default: inherited)")
    ap.add_argument("--out", type=Path, help=f"default {RESULTS.relative_to(ROOT)} ({RESULTS_CUDA.name} with --device cuda)")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one JSON config
    args = ap.parse_args(argv)
    if args.backends is None:
        args.backends = "cuda,torch" if args.device == "cuda" else "cpu,torch"
    if args.out is None:
        args.out = RESULTS_CUDA if args.device == "cuda" else RESULTS
    if args.one:
        print(json.dumps(run_one(json.loads(args.one))))
        return 0

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "src"), str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    )
    if args.omp_wait_policy:
        env["OMP_WAIT_POLICY"] = args.omp_wait_policy.upper()
    info = machine_info()
    info["threads"] = args.threads
    info["OMP_WAIT_POLICY"] = env.get("OMP_WAIT_POLICY", "(libgomp default)")
    rows = []
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            ap.error("--device cuda: this torch sees no CUDA device")
        info["gpu"] = torch.cuda.get_device_name(0)
    for cfg in configs(args.quick, args.threads, max(args.reps, 5), backends, args.device):
        if cfg["skip"]:
            rows.append(cfg)
            continue
        proc = subprocess.run([sys.executable, __file__, "--one", json.dumps(cfg)], env=env,
                              capture_output=True, text=True)
        if proc.returncode != 0:
            rows.append({**cfg, "error": proc.stderr.strip().splitlines()[-1:]})
            print(f"error in {cfg}: {proc.stderr[-2000:]}", file=sys.stderr)
            continue
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(res)
        print(f"{label(res):12s} {res['n']:>7d} {res['width']}x{res['height']} {res['backend']:5s}"
              f" fwd {res['fwd_ms']:8.1f} ms  fwd+bwd {res['fwd_bwd_ms']:8.1f} ms"
              f" (min {res['fwd_bwd_ms_min']:.1f}, CPU {res['fwd_bwd_cpu_ms']:.1f})"
              f"  peak {res.get('peak_cuda_mb', res['peak_rss_mb']):6.0f} MB  load {res['loadavg_1min'][1]:.1f}",
              flush=True)
    info["loadavg_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    payload = {"machine": info, "command": " ".join(["python", "benchmarks/raster.py", *sys.argv[1:]]),
               "results": rows}
    args.out.write_text(json.dumps(payload, indent=1) + "\n")
    print_table(rows)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from splatk._malloc import tune_malloc

    tune_malloc()  # what the `splatk` command does: timings match the CLI's
    raise SystemExit(main())
