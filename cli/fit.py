"""`splatk fit SCENE --out RUN`: reconstruct a scene from posed photos."""
from __future__ import annotations

import signal
from pathlib import Path

import click
from rich.console import Console

from splatk.stages.autobudget import AutoBudgetConfig
from splatk.stages.fit import FitConfig, boost_short_run_lrs, run_fit, scale_schedules_to_run

from .common import load_preset, parse_duration, resolve_options
from .progress import training_progress



@click.command("fit")
@click.argument("scene", type=click.Path(path_type=Path), required=False)
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="Run folder to write.")
@click.option("--preset", help="YAML preset name (presets/) or file; command line beats preset.")
@click.option("--kernel", type=click.Choice(["gaussian", "beta", "student_t", "learned"]), help="Splatting kernel. [default: gaussian]")
@click.option("--k", "k", type=int, help="Learned kernel: profile samples per primitive (2, 4, 8). [default: 2]")
@click.option("--kernel-weights", type=click.Path(path_type=Path), help="Learned kernel: pretrained networks from `splatk pretrain`.")
@click.option("--color", type=click.Choice(["sh", "sb"]), help="Colour model: spherical harmonics or spherical Beta. [default: sh]")
@click.option("--sh-degree", type=int, help="Maximum SH degree 0-3. [default: 3]")
@click.option("--primitive", type=click.Choice(["volumetric", "planar"]), help="Primitive type. [default: volumetric]")
@click.option("--backend", type=click.Choice(["auto", "torch", "cpu"]), help="Rasteriser backend. [default: auto]")
@click.option("--device", help="Torch device, e.g. cpu or cuda. [default: cpu]")
@click.option("--budget", help="Maximum number of primitives, or `auto` / `auto:N`: try N/2 (N: 100000) and double "
              "while a short run (a quarter of the iterations) at the doubled budget beats the previous one by "
              "> 0.5 dB on held-out train views, then train a fresh model at the chosen budget on every train view "
              "(as --budget N would); once growth ends, keep the fewest most-contributing primitives that hold the "
              "train-view PSNR within 0.6 dB, fine-tune them, and prune. [default: 100000]")
@click.option("--iters", type=int, help="Training iterations. [default: 30000]")
@click.option("--time-budget", help="Wall-clock training budget, e.g. 10m, 90s, 1h30m.")
@click.option("--downscale", type=float, help="Image downscale factor. [default: 1]")
@click.option("--init", "init", type=click.Choice(["auto", "sfm", "random"]),
              help="Initial primitives: SfM points, random, or auto (SfM points when the scene has them). [default: auto]")
@click.option("--seed", type=int, help="Random seed. [default: 0]")
@click.option("--threads", type=int, help="CPU threads (0: all). [default: 0]")
@click.option("--checkpoint-every", type=int, help="Checkpoint interval in iterations. [default: 1000]")
@click.option("--scale-schedules/--no-scale-schedules", default=None,
              help="Runs shorter than 30k iterations shrink the 30k step schedules (refine start and "
                   "interval, SH degree steps, learned-kernel freeze) in proportion and raise MCMC's "
                   "noise by 30k / iters (at most x10). [default: scale]")
@click.option("--short-run-lrs/--no-short-run-lrs", default=None,
              help="With --scale-schedules, also raise the LRs tuned for 30k iterations (log-scales, "
                   "learned latents and networks), as `splatk bench` does. [default: on]")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@click.option("--overwrite", is_flag=True, help="Replace an existing, non-empty --out folder.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.pass_context
def command(ctx, scene, out, preset, resume, overwrite, quiet, **opts):
    """Reconstruct SCENE (COLMAP sparse/0 + images/, or transforms*.json) into RUN."""
    if scene is None and not resume:
        raise click.UsageError("SCENE is required (unless --resume)")
    values, sources = resolve_options(ctx, opts, load_preset(preset))
    cfg = build_fit_config(values)
    if not resume:
        changed = {}
        if values.get("scale_schedules") is not False:  # as `splatk bench` does
            changed = scale_schedules_to_run(cfg)
            if values.get("short_run_lrs") is not False:
                changed.update(boost_short_run_lrs(cfg))
        for key, value in changed.items():
            sources[key] = f"scaled to the run length ({cfg.train.iters} of 30000 iterations): {value}"
    console = Console(stderr=True)
    progress = None if quiet else training_progress(console)
    task = {}

    def on_start(info):
        task["started"] = True
        s = info["scene"]
        console.print(
            f"[bold]splatk fit[/] {s.root}: {len(s.train)} train / {len(s.test)} test views "
            f"{s.train[0].width}x{s.train[0].height}, {info['model'].num_primitives:,} initial primitives, "
            f"kernel {cfg.kernel}, backend {cfg.train.backend}"
        )
        if progress is not None:
            progress.start()
            task["id"] = progress.add_task("fit", total=info["iters"], completed=info["start_it"],
                                           loss=0.0, psnr=0.0, num=info["model"].num_primitives, rate=0.0)

    def on_step(info):
        if info.event:
            console.print(f"[yellow]{info.event}")
        if progress is not None and (info.it % 10 == 0 or info.it == info.iters):
            rate = info.it / info.elapsed if info.elapsed > 0 else 0.0
            total = info.iters
            if cfg.train.time_budget and rate > 0:
                total = min(info.iters, max(info.it, int(rate * cfg.train.time_budget)))
            progress.update(task["id"], completed=info.it, total=total, loss=info.loss, psnr=info.psnr,
                            num=info.num_primitives, rate=rate)

    stop = {"flag": False, "signal": None}

    def handle_signal(signum, frame):
        # SIGTERM and the first Ctrl-C stop at the next iteration boundary, so the checkpoint
        # holds whole iterations (a KeyboardInterrupt can land inside density control, between
        # two tensors' updates); a second Ctrl-C, or one before training started, stops at once
        if signum == signal.SIGINT and (stop["flag"] or not task.get("started")):
            raise KeyboardInterrupt
        stop["flag"], stop["signal"] = True, signum

    old = signal.signal(signal.SIGTERM, handle_signal)
    old_int = signal.signal(signal.SIGINT, handle_signal)
    try:
        run = run_fit(scene, out, cfg, overwrite=overwrite, resume=resume, config_sources=sources,
                      on_start=on_start, on_step=on_step, should_stop=lambda: stop["flag"])
    except KeyboardInterrupt:
        if progress is not None:
            progress.stop()
        if task.get("started"):
            console.print(f"[yellow]interrupted; checkpoint saved, continue with: splatk fit --resume --out {out}")
        raise SystemExit(130)
    finally:
        signal.signal(signal.SIGTERM, old)
        signal.signal(signal.SIGINT, old_int)
        if progress is not None:
            progress.stop()
    if cfg.auto_budget is not None:
        import json

        rep = json.loads((run / "fit.json").read_text()).get("auto_budget") or {}
        stages = ", ".join(f"{st['budget']:,}: {st['holdout_psnr']:.2f} dB" for st in rep.get("stages", []))
        prune = rep.get("prune") or {}
        comp = rep.get("compact")
        compact = (f"; compacted {comp['num_primitives_before']:,} -> {comp['num_primitives_after']:,} "
                   f"(train views {comp['train_psnr_before']:.2f} -> {comp['train_psnr_after']:.2f} dB)" if comp else "")
        refit = (f"; refit at it from the start on every train view (selection took "
                 f"{rep['selection_seconds']:.0f} s)" if rep.get("refit") and rep.get("selection_seconds") else "")
        console.print(f"auto budget: chose {rep.get('chosen_budget')} ({stages}){refit}{compact}; "
                      f"pruned {prune.get('pruned', 0)} primitives")
    console.print(f"wrote {run / 'model.pt'}")
    if stop["signal"] == signal.SIGINT:
        console.print(f"[yellow]stopped by Ctrl-C; checkpoint saved, continue with: splatk fit --resume --out {out}")
        raise SystemExit(130)


def build_fit_config(values: dict) -> FitConfig:
    cfg = FitConfig()
    v = {k: x for k, x in values.items() if x is not None}
    for name in ("kernel", "color", "sh_degree", "primitive", "backend", "device", "downscale", "threads",
                 "checkpoint_every"):
        if name in v:
            setattr(cfg, name, v[name])
    if "k" in v:
        cfg.kernel_options["k"] = int(v["k"])
    if "kernel_weights" in v:
        cfg.kernel_options["weights"] = str(v["kernel_weights"])
    t = cfg.train
    if "budget" in v and str(v["budget"]).strip().lower().startswith("auto"):
        cfg.auto_budget = AutoBudgetConfig()  # sizes relative to the reference budget
        ref = str(v["budget"]).strip()[4:].lstrip(":")
        if ref:
            try:
                t.budget = int(float(ref))
            except ValueError:
                raise click.BadParameter(f"--budget {v['budget']!r}: use auto or auto:N (N primitives)") from None
    elif "budget" in v:
        try:
            t.budget = int(float(v["budget"]))
        except ValueError:
            raise click.BadParameter(f"--budget {v['budget']!r}: give a number of primitives or auto") from None
    for name in ("iters", "seed", "init"):
        if name in v:
            setattr(t, name, v[name])
    if "time_budget" in v:
        t.time_budget = parse_duration(v["time_budget"])
        if "iters" not in v:
            t.iters = 10**9  # the clock decides
    t.backend = cfg.backend
    t.device = cfg.device
    return cfg
