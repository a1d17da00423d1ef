"""`splatk bench SCENES... --out OUT`: a grid of methods over scenes, charts, stability matrix."""
from __future__ import annotations

import fnmatch
import json
from pathlib import Path

import click
from rich import box
from rich.console import Console
from rich.table import Table

from splatk.backends import backend_names
from splatk.colors import COLOR_MODELS
from splatk.device import resolve_device
from splatk.kernels import kernel_names
from splatk.kernels.auto_k import AUTO_K
from splatk.stages.fit_config import PRIMITIVES, parse_duration
from splatk.bench.methods import protocol_departures
from splatk.bench import (
    STABILITY_CONDITIONS,
    STABILITY_KERNELS,
    BenchConfig,
    BenchStopped,
    load_bench_file,
    load_results,
    method_id,
    run_bench,
    run_stability,
    table_rows,
)

from .common import find_preset, signal_name, stop_requests

# single-valued flags that go into every method's defaults (flag name -> settings key)
_DEFAULT_FLAGS = ("iters", "time_budget", "downscale", "threads", "init", "backend", "device", "seed",
                  "sh_degree", "primitive")


@click.command("bench")
@click.argument("scenes", nargs=-1, type=click.Path(path_type=Path))
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True,
              help="Bench folder: runs/, results/ (one JSON per run), charts/.")
@click.option("--preset", "--methods", "preset",
              help="Bench YAML (presets/bench_*.yaml name or a file): defaults, methods/grid, scenes, stability.")
@click.option("--kernel", multiple=True, type=click.Choice(kernel_names("volumetric")),
              help="Kernel(s) of the grid (repeat). Replaces the YAML's methods.")
@click.option("--k", "ks", multiple=True, help="Learned kernel: k value(s) (repeat), or auto. [default: auto]")
@click.option("--weights", help="Learned kernel weights for flag-built methods: default, a file, or none.")
@click.option("--color", multiple=True, type=click.Choice(sorted(COLOR_MODELS)), help="Colour model(s) (repeat).")
@click.option("--budget", multiple=True, help="Primitive budget(s) (repeat), or auto.")
@click.option("--budget-bytes", multiple=True,
              help="Memory budget(s), e.g. 4MB (repeat): budget = (bytes - network bytes) // bytes per primitive.")
@click.option("--only", multiple=True,
              help="Run only the methods whose id matches this pattern (repeat; shell wildcards), e.g. "
                   "'learned-k8-*' for one column of a preset's grid.")
@click.option("--iters", type=int, help="Training iterations of every run.")
@click.option("--time-budget", help="Wall-clock training budget of every run, e.g. 90s, 5m.")
@click.option("--downscale", type=float, help="Image downscale factor.")
@click.option("--threads", type=int, help="CPU threads per run (0: all). Recorded in every result.")
@click.option("--init", type=click.Choice(["auto", "sfm", "random"]), help="Initial primitives.")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), help="Rasteriser backend.")
@click.option("--device", help="Torch device every run fits and is evaluated on: cpu, cuda, cuda:N. [default: cpu]")
@click.option("--seed", type=int, help="Random seed.")
@click.option("--sh-degree", type=int, help="Maximum SH degree.")
@click.option("--primitive", type=click.Choice(PRIMITIVES),
              help="Primitive type of every method (planar: gaussian and learned kernels only). [default: volumetric]")
@click.option("--metrics", help="Comma-separated: psnr,ssim,lpips. [default: psnr,ssim,lpips]")
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), help="LPIPS network. [default: alex]")
@click.option("--no-scale-schedules", is_flag=True,
              help="Keep 30k-iteration schedules (refine start/interval, SH steps, learned freeze, MCMC noise) in short runs.")
@click.option("--stability", is_flag=True,
              help="Run the stability matrix (kernels x conditions) instead of the method grid.")
@click.option("--charts-only", is_flag=True, help="Only redraw the charts and table from OUT/results.")
@click.option("--quiet", "-q", is_flag=True, help="No per-run progress lines.")
def command(scenes, out, preset, kernel, ks, weights, color, budget, budget_bytes, only, metrics, lpips_net,
            no_scale_schedules, stability, charts_only, quiet, **flags):
    """Fit and evaluate every method on every SCENE into OUT; resumable (finished runs are
    skipped, and a method whose settings equal a finished run's, e.g. `--k auto` choosing a k
    the grid also lists, reports that run instead of training it again); draws PSNR vs render
    time / training time / footprint with the Pareto front.
    SIGTERM or Ctrl-C stops the fit in progress at its next iteration with a checkpoint (exit
    128 + the signal); the same command goes on from there.

    \b
    Examples:
      splatk bench SCENE --out B --kernel gaussian --kernel learned --k 2 --k 8 --budget 20000 --iters 2000
      splatk bench SCENE --out B --preset bench_kernels --downscale 2
      splatk bench SCENE --out B --stability --preset bench_stability
    """
    console = Console(stderr=True)
    data = load_bench_file(find_preset(preset)) if preset else {}
    scenes = [str(s) for s in scenes] or data.get("scenes") or []
    defaults = dict(data.get("defaults") or {})
    for name in _DEFAULT_FLAGS:
        if flags.get(name) is not None:
            defaults[name] = flags[name]
    if "device" in defaults:  # a missing GPU is one line now, not a failed row per run later
        resolve_device(defaults["device"], defaults.get("backend", "auto"))
    if "time_budget" in defaults:
        try:
            defaults["time_budget"] = parse_duration(defaults["time_budget"])
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--time-budget") from None
    methods = list(data.get("methods") or [])
    check_grid_flags(kernel, ks, weights, color, budget, budget_bytes, only, stability, methods)
    if kernel:
        methods = build_methods(kernel, ks, weights, color, budget, budget_bytes)
    elif budget or budget_bytes or color or ks:
        # flags without --kernel: apply to the YAML's methods (or to a plain gaussian)
        methods = [_override(m, o) for m in (methods or [{"kernel": "gaussian"}])
                   for o in _overrides(ks, color, budget, budget_bytes)]
        unique = {json.dumps(m, sort_keys=True): m for m in methods}  # e.g. YAML budgets replaced by one flag
        methods = list(unique.values())
    if only:
        ids = [method_id(m, defaults) for m in methods]
        methods = [m for m, i in zip(methods, ids) if any(fnmatch.fnmatchcase(i, p) for p in only)]
        if not methods:
            raise click.BadParameter(f"no method id matches {', '.join(only)}; the ids are {', '.join(ids)}",
                                     param_hint="--only")
    metric_names = tuple(m.strip() for m in (metrics or ",".join(data.get("metrics") or ["psnr", "ssim", "lpips"]))
                         .split(",") if m.strip())
    bad = [m for m in metric_names if m not in ("psnr", "ssim", "lpips")]
    if bad:
        raise click.BadParameter(f"unknown metric(s): {', '.join(bad)}", param_hint="--metrics")
    scale_schedules = not no_scale_schedules and data.get("scale_schedules", True)
    departures = protocol_departures(data, defaults, scale_schedules)
    if departures:  # a shortened protocol is a different experiment: say so before it runs
        console.print(f"[yellow]not {data['protocol'].get('name', 'the protocol')}'s protocol: "
                      f"{'; '.join(departures)}; compare these results with the paper's only as such")
    cfg = BenchConfig(methods=methods, defaults=defaults, metrics=metric_names,
                      lpips_net=lpips_net or data.get("lpips_net", "alex"),
                      scale_schedules=scale_schedules)

    def on_event(kind, info):
        if quiet:
            return
        extra = ""
        if kind == "done":
            extra = f": {info['psnr']:.2f} dB, {info['train_seconds']:.1f} s training"
        elif kind == "failed":
            extra = f": {info['error']}"
        elif kind == "same run":
            extra = f": the finished run of {info['as']} (the same settings)"
        console.print(f"[bold]{kind:>9}[/] {info['scene']} / {info['method']}{extra}")

    if charts_only and not stability:
        from splatk.bench.charts import draw_pareto_charts, draw_stability_heatmap

        rows = load_results(Path(out) / "results")
        paths = draw_pareto_charts(rows, Path(out) / "charts")
        for mp in sorted((Path(out) / "stability").glob("matrix_*.json")):
            matrix = json.loads(mp.read_text())
            paths += draw_stability_heatmap(matrix, Path(out) / "charts" / f"stability_{matrix['scene']}")
        print_table(rows)
        for p in paths:
            console.print(f"wrote {p}")
        return

    with stop_requests() as stop:
        should_stop = lambda: stop["signal"] is not None  # noqa: E731
        try:
            if stability:
                st = data.get("stability") or {}
                base = {**defaults, **(st.get("defaults") or {})}
                for name in _DEFAULT_FLAGS:  # the command line still wins
                    if flags.get(name) is not None:
                        base[name] = defaults[name]
                if budget:
                    base["budget"] = budget[0]
                cfg.defaults = base
                res = run_stability(scenes, cfg, out, kernels=st.get("kernels") or STABILITY_KERNELS,
                                    conditions=st.get("conditions") or STABILITY_CONDITIONS, on_event=on_event,
                                    should_stop=should_stop)
                print_stability(res.rows)
            else:
                res = run_bench(scenes, cfg, out, on_event=on_event, should_stop=should_stop)
                print_table(res.rows)
        except BenchStopped as e:
            # a stopped bench is not a finished one: schedulers and `timeout` must see that
            kept = f"; {e.run} keeps its checkpoint" if e.run else ""
            console.print(f"[yellow]stopped by {signal_name(stop['signal'])}: finished runs keep their "
                          f"results{kept}; the same command goes on from there")
            raise SystemExit(128 + stop["signal"])
    for p in res.charts:
        console.print(f"wrote {p}")


def check_grid_flags(kernel, ks, weights, color, budget, budget_bytes, only, stability, methods) -> None:
    """A grid flag that would change nothing is an error, not silently dropped: --stability runs
    its own kernels and conditions, --weights shapes flag-built learned methods, --k learned ones."""
    if stability:
        given = [name for name, value in (("--only", only), ("--kernel", kernel), ("--k", ks), ("--weights", weights),
                                          ("--color", color), ("--budget-bytes", budget_bytes)) if value]
        if given:
            raise click.BadParameter("--stability runs its own kernels and conditions (the bench file's "
                                     "stability: section sets them)", param_hint=given[0])
        if len(budget) > 1:
            raise click.BadParameter("--stability trains every cell at one budget", param_hint="--budget")
        return
    if weights and "learned" not in kernel:
        raise click.BadParameter("sets the weights of the flag-built learned methods (add --kernel learned)",
                                 param_hint="--weights")
    learned = "learned" in kernel if kernel else any(m.get("kernel") == "learned" for m in methods)
    if ks and not learned:
        raise click.BadParameter("sets the learned kernel's k, and no method of the grid is learned "
                                 "(add --kernel learned)", param_hint="--k")


def _override(method: dict, o: dict) -> dict:
    m = dict(method)
    if "budget" in o or "budget_bytes" in o:  # a flag budget replaces either kind of YAML budget
        m.pop("budget", None)
        m.pop("budget_bytes", None)
    if "k" in o and m.get("kernel") != "learned":
        o = {key: v for key, v in o.items() if key != "k"}
    return {**m, **o}


def _overrides(ks, color, budget, budget_bytes) -> list[dict]:
    from splatk.bench import expand_grid

    grid: dict = {}
    if ks:
        grid["k"] = list(ks)
    if color:
        grid["color"] = list(color)
    if budget_bytes:
        grid["budget_bytes"] = list(budget_bytes)
    elif budget:
        grid["budget"] = list(budget)
    return expand_grid(grid) if grid else [{}]


def build_methods(kernels, ks, weights, colors, budgets, budget_bytes) -> list[dict]:
    """The grid of flag-built methods: kernels (learned x each k) x colours x budgets."""
    kern = []
    for k in kernels:
        if k == "learned":
            for kv in (ks or (AUTO_K,)):
                m = {"kernel": "learned", "k": kv}
                if weights:
                    m["weights"] = weights
                kern.append(m)
        else:
            kern.append({"kernel": k})
    out = []
    for m in kern:
        for o in _overrides((), colors, budgets, budget_bytes):
            out.append({**m, **o})
    return out


def _f(x, fmt="{:.2f}"):
    return "n/a" if not isinstance(x, (int, float)) else fmt.format(x)


def print_table(rows: list[dict]) -> None:
    """One table per scene (PSNRs of different scenes do not compare)."""
    console = Console()
    for scene in sorted({r.get("scene", "") for r in rows}):
        table = Table(title=f"splatk bench: {scene}", box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False)
        table.add_column("method", overflow="fold", min_width=20)
        # numbers never wrap (a narrow terminal folds the method names instead)
        for col in ("PSNR", "SSIM", "LPIPS", "train s", "ms/view", "MB", "prims"):
            table.add_column(col, justify="right", no_wrap=True)
        for r in table_rows(rows):
            if r["scene"] != scene:
                continue
            if r["status"] != "ok":
                table.add_row(r["method"], f"[red]{r['status']}", *[""] * 6)
                continue
            table.add_row(r["method"], _f(r["psnr"]), _f(r["ssim"], "{:.3f}"), _f(r["lpips"], "{:.3f}"),
                          _f(r["train_seconds"], "{:.1f}"), _f(r["render_ms"], "{:.1f}"),
                          _f(r["footprint_mb"], "{:.2f}"), _f(r["num_primitives"], "{:,}"))
        console.print(table)
        threads = sorted({str(r.get("threads")) for r in rows if r.get("scene") == scene and r.get("status") == "ok"})
        console.print(f"  torch threads per run: {', '.join(threads) or 'n/a'} (wall-clock timings on this machine)")


def print_stability(rows: list[dict]) -> None:
    table = Table(title="splatk bench --stability", box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False)
    for col in ("scene", "kernel", "condition", "PSNR", "initial", "NaN", "flags"):
        table.add_column(col, no_wrap=col in ("kernel", "condition"))
    for r in rows:
        flags = [name for name in ("diverged", "below_initial", "collapsed") if r.get(name)]
        if r.get("status") != "ok":
            flags = [r.get("status", "")]
        table.add_row(r.get("scene", ""), r.get("row", ""), r.get("col", ""), _f(r.get("psnr")),
                      _f(r.get("initial_psnr")), str(r.get("nan_rollbacks", "")), ", ".join(flags))
    Console().print(table)
