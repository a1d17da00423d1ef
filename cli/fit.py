"""`splatk fit SCENE --out RUN`: reconstruct a scene from posed photos."""
from __future__ import annotations

import os
import signal
import sys
import traceback
from pathlib import Path

import click

from splatk.backends import backend_names
from splatk.data import EVAL_SPLITS
from splatk.errors import InputError, TrainingStalled
from splatk.train.distributed import WorkerLost, launch_local, launched_world
from splatk.kernels import kernel_names
from splatk.colors import COLOR_MODELS
from splatk.train.strategies import STRATEGIES
from splatk.stages.fit import run_fit
from splatk.stages.fit_config import PRIMITIVES, fit_config_from_options

from .common import load_preset, resolve_options, signal_name, stop_requests
from .progress import DEFAULT_LOG_EVERY, stderr_console, training_progress


@click.command("fit")
@click.argument("scene", type=click.Path(path_type=Path), required=False)
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="Run folder to write.")
@click.option("--preset", help="YAML preset name (presets/) or file; command line beats preset.")
@click.option("--kernel", type=click.Choice(kernel_names()), help="Splatting kernel. [default: gaussian]")
@click.option("--k", "k", help="Learned kernel: profile samples per primitive (2, 4, 8), or `auto`: the k the "
              "scene's pixels per primitive call for (decisions 0102, 0105). [default: auto]")
@click.option("--kernel-weights", type=click.Path(path_type=Path), help="Learned kernel: pretrained networks from `splatk pretrain`.")
@click.option("--color", type=click.Choice(sorted(COLOR_MODELS)), help="Colour model: spherical harmonics or spherical Beta. [default: sh]")
@click.option("--sh-degree", type=int, help="Maximum SH degree 0-3. [default: 3]")
@click.option("--primitive", type=click.Choice(PRIMITIVES), help="Primitive type. [default: volumetric]")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), help="Rasteriser backend. [default: auto]")
@click.option("--device", help="Torch device, e.g. cpu or cuda. [default: cpu]")
@click.option("--batch-views", type=int,
              help="Train views per step, their losses averaged; the learning rates rise by sqrt(B) "
                   "(Grendel-GS's rule). [default: 1]")
@click.option("--strategy", type=click.Choice(sorted(STRATEGIES)),
              help="Density control: mcmc (DBS / 3DGS-MCMC: relocate, grow to --budget) or adc (3DGS: clone, "
                   "split, prune, opacity reset until 15k of 30k iterations; grows without a cap unless --budget or --budget-bytes is given; no opacity or scale regulariser unless given; starts as 3DGS: opacity 0.1, scales at the neighbour spacing, random init 100k points). [default: mcmc]")
@click.option("--budget", help="Maximum number of primitives, or `auto` / `auto:N`: try N/2 (N: 100000) and double "
              "while a short run (a quarter of the iterations) at the doubled budget beats the previous one by "
              "> 0.5 dB on held-out train views, then train a fresh model at the chosen budget on every train view "
              "(as --budget N would); once growth ends, keep the fewest most-contributing primitives that hold the "
              "train-view PSNR within 0.6 dB, fine-tune them, and prune. [default: 100000]")
@click.option("--budget-bytes", help="Memory for the model instead of --budget: the number of primitives follows "
              "from the bytes each takes and the kernel's networks (4194304, 4MB, 512KB).")
@click.option("--iters", type=int, help="Training iterations. [default: 30000]")
@click.option("--time-budget", help="Wall-clock training budget, e.g. 10m, 90s, 1h30m.")
@click.option("--downscale", type=float, help="Image downscale factor; a whole number N reads images_N/ where the "
              "scene has it. [default: 1]")
@click.option("--test-every", type=int, help="Every N-th image (name order) is a test view when the dataset names "
              "no test list. [default: 8]")
@click.option("--eval-split", type=click.Choice(EVAL_SPLITS),
              help="Test views: held-out (the dataset's test list, else every --test-every-th view), all (every "
                   "view trains and is evaluated), none (every view trains; `splatk eval` then needs --split "
                   "train). [default: held-out]")
@click.option("--background", type=click.Choice(["white", "black", "random"]),
              help="Colour RGBA images are composited on and renders use; random: a new colour every training "
                   "step (RGBA images recomposited on it), the default colour for evaluation. [default: white "
                   "for transforms.json scenes, black for COLMAP]")
@click.option("--normal-weight", type=float,
              help="Planar primitives: weight of 2DGS's normal consistency (blended surfel normals against "
                   "the rendered depth's normals; 2DGS: 0.05), on after 7000 of 30k iterations. [default: 0]")
@click.option("--distortion-weight", type=float,
              help="Planar primitives: weight of the depth distortion (blended variance of inverse depth along "
                   "each ray; 2DGS's L1 form takes 1000 on DTU, 10-100 on Tanks and Temples), on after 3000 of "
                   "30k iterations. [default: 0]")
@click.option("--opacity-reg", type=float,
              help="Weight of the mean-opacity regulariser (DBS / 3DGS-MCMC). [default: 0.01; 0 with "
                   "--strategy adc]")
@click.option("--scale-reg", type=float,
              help="Weight of the mean-scale regulariser (DBS / 3DGS-MCMC). [default: 0.01; 0 with "
                   "--strategy adc]")
@click.option("--init", "init", type=click.Choice(["auto", "sfm", "random"]),
              help="Initial primitives: SfM points, random, or auto (SfM points when the scene has them). [default: auto]")
@click.option("--seed", type=int, help="Random seed. [default: 0]")
@click.option("--threads", type=int, help="CPU threads (0: all). [default: 0]")
@click.option("--nproc", type=int,
              help="Training processes on this machine (data parallel, torch.distributed: gloo on CPU, NCCL "
                   "on CUDA): each renders its share of a step's --batch-views views (default: one each). "
                   "Under torchrun, the launcher's processes instead. [default: 1]")
@click.option("--checkpoint-every", type=int, help="Checkpoint interval in iterations. [default: 1000]")
@click.option("--scale-schedules/--no-scale-schedules", default=None,
              help="Runs shorter than 30k iterations shrink the 30k step schedules (refine start and "
                   "interval, SH degree steps, learned-kernel freeze, planar geometry terms' starts) in "
                   "proportion and raise MCMC's "
                   "noise by 30k / iters (at most x10). [default: scale]")
@click.option("--short-run-lrs/--no-short-run-lrs", default=None,
              help="With --scale-schedules, also raise the LRs tuned for 30k iterations (log-scales, "
                   "learned latents and networks), as `splatk bench` does. [default: on]")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint. Options given "
              "with it must equal the run's, except --iters, --time-budget, --checkpoint-every, --threads, "
              "--backend and --device, which change the run from here on (recorded in config.yaml).")
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False,
              help="Replace --out if it is a run folder splatk wrote (never any other folder; not read from "
                   "the environment).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--log-every", type=click.FloatRange(min=0), default=DEFAULT_LOG_EVERY, show_default=True,
              metavar="SECONDS", help="When stderr is not a terminal (a log file, a batch job, CI): print a plain "
              "progress line (iteration/total, loss, PSNR, primitives, it/s, ETA) this often instead of the bar.")
@click.pass_context
def command(ctx, scene, out, preset, resume, overwrite, quiet, log_every, **opts):
    """Reconstruct SCENE (COLMAP sparse/0 + images/, or transforms*.json) into RUN.

    SCENE layouts: COLMAP (sparse/0 or sparse/ + images/; pinhole, OpenCV and fisheye camera
    models; Mip-NeRF 360, and Tanks & Temples and Deep Blending as the 3DGS repository ships
    them), NeRF-synthetic (transforms_train.json + transforms_test.json, whose test list is the
    test split) and instant-ngp / nerfstudio (transforms.json; camera_model OPENCV_FISHEYE,
    mask_path: black pixels leave the loss and the metrics, ply_file_path: the initial points).
    Every camera is undistorted to a pinhole. --downscale N (a whole number) reads images_N/
    beside images/ when it exists, scaling the intrinsics by the actual size ratio; an image
    there that is not 1/N of its original is an error naming the folder. A dataset field splatk
    does not read is named in a warning. Edge rows or columns black in every image (video
    padding, letterboxing) and the row beside them leave the loss and the metrics, with a
    warning that names them.

    RUN/train_log.jsonl gets a JSON line every 100 iterations and at every training event, with
    the fields it (iteration), loss (training loss), psnr (PSNR in dB of that iteration's training
    view), num (primitives), elapsed (training seconds so far, resumed runs included), event
    (null, or a message: a rollback and its halved step size, the loss check turned off, MCMC
    growth held), normal_loss (2DGS's normal consistency) and distortion_loss (the depth
    distortion): with --primitive planar and --normal-weight or --distortion-weight, each term
    unweighted and averaged over the step's views once it is on, else null.
    """
    if scene is None and not resume:
        raise click.UsageError("SCENE is required (unless --resume)")
    preset_values, preset_path = load_preset(preset)
    values, sources = resolve_options(ctx, opts, preset_values, preset_path)
    resume_options = None
    if resume:
        # what the user asked for now; the run's own settings come from its config.yaml
        resume_options = {k: v for k, v in values.items() if sources[k] != "default"}
        cfg = None
    else:
        cfg, notes = fit_config_from_options(values, sources)
        changed = {k: v for k, v in notes.get("scaled_schedules", {}).items() if k != "factor"}
        for key, value in changed.items():
            sources[key] = f"scaled to the run length ({cfg.train.iters} of 30000 iterations): {value}"
    job = dict(scene=scene, out=out, cfg=cfg, sources=sources, overwrite=overwrite, resume=resume,
               resume_options=resume_options, quiet=quiet, log_every=log_every)
    nproc = values.get("nproc") or 1
    if nproc > 1 and not launched_world().distributed:
        _launch(nproc, job)
    else:
        _fit_here(**job)


#: exit code of a worker whose job lost another worker (2: bad input, 3: training stalled)
EXIT_WORKER_LOST = 4


def _launch(nproc: int, job: dict) -> None:
    """``--nproc N``: N workers on this machine, each running the fit as one rank. Each worker
    prints its own error; a worker killed by a signal could not, so it is named here. The exit
    code is rank 0's, else the first failed worker's (128 + N for signal N)."""
    failed = launch_local(nproc, _worker, job)
    for rank, code in sorted(failed.items()):
        if code < 0:
            name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else f"signal {-code}"
            click.echo(f"splatk: error: worker {rank} was killed ({name}); the last checkpoint in "
                       f"{Path(job['out']) / 'checkpoints'} is intact: continue with `splatk fit --resume --out "
                       f"{job['out']}`", err=True)
    if failed:
        code = failed[min(failed)]
        sys.exit(128 - code if code < 0 else code)


def _worker(job: dict) -> None:
    """One rank of `fit --nproc N` (a launcher's worker process). A failure that is no input
    error keeps its traceback: the launcher's own report of it is silenced."""
    try:
        _fit_here(**job)
    except Exception:  # noqa: BLE001 - a bug: show where, then stop this rank
        traceback.print_exc()
        sys.stderr.flush()
        os._exit(1)


def _fit_here(scene, out, cfg, sources, overwrite, resume, resume_options, quiet, log_every) -> None:
    """The fit in this process: alone, or as one rank of a job (rank 0 alone prints progress)."""
    world = launched_world()
    try:
        _fit_and_report(scene, out, cfg, sources, overwrite, resume, resume_options, quiet or not world.main,
                        log_every, world.main)
        return
    except WorkerLost as e:
        code, message = EXIT_WORKER_LOST, (
            f"worker {world.rank}: another worker of the job stopped ({e}); the last checkpoint in "
            f"{Path(out) / 'checkpoints'} is intact: continue with `splatk fit --resume --out {out}`")
    except (InputError, TrainingStalled) as e:
        if not world.distributed:
            raise
        code, message = 2 if isinstance(e, InputError) else 3, e.message()
    click.echo(f"splatk: error: {message}", err=True)
    if not world.distributed:
        sys.exit(code)
    sys.stdout.flush()
    sys.stderr.flush()
    # a rank whose peers have gone can abort in the collective library's teardown at
    # interpreter exit (SIGABRT instead of this exit code): leave at once
    os._exit(code)


def _fit_and_report(scene, out, cfg, sources, overwrite, resume, resume_options, quiet, log_every, main) -> None:
    console = stderr_console()
    progress = None if quiet else training_progress(console, log_every)
    task = {}

    def on_start(info):
        task["started"] = True
        if not main:
            return
        s, run_cfg = info["scene"], info["config"]
        for w in s.warnings:  # what the loader read past without using
            console.print(f"[yellow]warning: {w}")
        if s.test_listed and sources.get("test_every") == "command line":
            console.print(f"[yellow]warning: --test-every {run_cfg.test_every}: {s.root} lists its own test views "
                          "(transforms_test.json); ignored")
        console.print(
            f"[bold]splatk fit[/] {s.root}: {len(s.train)} train / {len(s.test)} test views "
            f"{s.train[0].width}x{s.train[0].height}, {info['model'].num_primitives:,} initial primitives, "
            f"kernel {run_cfg.kernel}{_k_text(run_cfg)}, backend {run_cfg.train.backend}"
        )
        task["time_budget"] = run_cfg.train.time_budget
        task["auto_budget"] = run_cfg.auto_budget is not None
        if progress is not None:
            progress.start()
            task["id"] = progress.add_task("fit", total=info["iters"], completed=info["start_it"],
                                           loss=0.0, psnr=0.0, num=info["model"].num_primitives, rate=0.0)

    def on_step(info):
        if info.event and main:
            console.print(f"[yellow]{info.event}")
        if progress is not None and (info.it % 10 == 0 or info.it == info.iters):
            rate = info.it / info.elapsed if info.elapsed > 0 else 0.0
            total = info.iters
            time_budget = task["time_budget"]
            if time_budget and rate > 0:
                total = min(info.iters, max(info.it, int(rate * time_budget)))
            progress.update(task["id"], completed=info.it, total=total, loss=info.loss, psnr=info.psnr,
                            num=info.num_primitives, rate=rate)

    try:
        # Ctrl-C before training started stops at once: there is nothing to checkpoint yet
        with stop_requests(at_once=lambda: not task.get("started")) as stop:
            result = run_fit(scene, out, cfg, overwrite=overwrite, resume=resume, config_sources=sources,
                             on_start=on_start, on_step=on_step, should_stop=lambda: stop["signal"] is not None,
                             resume_options=resume_options)
    except KeyboardInterrupt:
        if progress is not None:
            progress.stop()
        if task.get("started") and main:
            console.print(f"[yellow]interrupted; checkpoint saved, continue with: splatk fit --resume --out {out}")
        raise SystemExit(130)
    finally:
        if progress is not None:
            progress.stop()
    run = result.path
    if not main:
        if stop["signal"] is not None:
            raise SystemExit(128 + stop["signal"])
        return
    if task.get("auto_budget"):
        rep = result.summary.get("auto_budget") or {}
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
    if stop["signal"] is not None:
        # a stopped run is not a finished one: schedulers and `timeout` must see that
        console.print(f"[yellow]stopped by {signal_name(stop['signal'])}; checkpoint saved, "
                      f"continue with: splatk fit --resume --out {out}")
        raise SystemExit(128 + stop["signal"])


def _k_text(cfg) -> str:
    k = cfg.kernel_options.get("k")
    return f" (k = {k})" if cfg.kernel == "learned" and k is not None else ""
