"""`splatk fit`: scene folder -> trained model in a run folder.

Run folder layout::

    RUN/config.yaml          resolved settings, with where each value came from
    RUN/checkpoints/last.pt  full training state, written atomically every N iterations
    RUN/model.pt             final model (native format; `splatk export` converts it)
    RUN/fit.json             summary: iterations, wall time, primitives, events (NaN rollbacks),
                             test PSNR of the initial model, the auto-budget report
    RUN/train_log.jsonl      loss / PSNR / primitive count every 100 iterations
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch
import yaml

from ..data import load_scene
from ..errors import InputError, TrainingStalled
from ..backends import GAUSSIAN_SUPPORT_SIGMAS
from ..device import resolve_device
from ..kernels import KERNELS, make_kernel
from ..models.init import initial_points
from ..models.io import atomic_torch_save, model_spec, save_model
from ..models.planar import PlanarModel
from ..models.volumetric import SplatModel
from ..outputs import OutputDir, check_output_dir
from ..train.mcmc import MCMCConfig
from ..train.trainer import StepInfo, TrainConfig, Trainer
from .autobudget import AutoBudget, render_psnr, split_holdout
from .fit_config import (PRIMITIVES, FitConfig, check_fit_config, color_options as _color_options,
                         fit_config_from_options)

#: the marker kind of a run folder (``splatk.outputs``)
RUN_KIND = "fit run"
#: settings ``fit --resume`` may change; every other one given on resume must equal the run's
RESUME_CHANGEABLE = ("iters", "time_budget", "checkpoint_every", "threads", "backend", "device")


#: the paper's run length; the step-count schedules below are tuned for it
FULL_ITERS = 30_000
#: step-count schedules at 30k iterations: (value, smallest value when scaled to a shorter run)
RUN_LENGTH_SCHEDULES = {"refine_start": (500, 0), "refine_every": (100, 5), "sh_degree_interval": (1000, 1)}
#: the learned kernel freezes its networks for this many of the 30k iterations (paper Sec. 4.5)
LEARNED_FREEZE_ITERS = 2000
#: short runs raise MCMC's position noise (DBS's noise_lr, tuned for 30k iterations) by
#: 30k / iters, at most this much
NOISE_LR_MULT_MAX = 10.0


def scale_schedules_to_run(cfg: "FitConfig", keep: frozenset | set = frozenset()) -> dict:
    """Shrink the step-count schedules of a run shorter than 30k iterations in proportion
    (gsplat's ``steps_scaler`` idea); returns {setting: new value} (empty when nothing changed).

    Unscaled, a 2000-iteration run would refine only every 100 steps, so MCMC's 5% growth per
    refine could not reach the budget (a quarter-budget random init ends near 43% of it), raise
    the SH degree twice, and leave a learned kernel's networks frozen for the whole run.
    MCMC's position noise grows by 30k / iters (at most x10): the means get that many fewer
    gradient steps, and the noise is what moves near-transparent primitives to where they are
    needed (benchmarks/README.md, "MCMC noise in short runs": fox, random init, 2000 iterations,
    +2.3 dB over two seeds). Runs with a time budget are left alone (their schedules follow
    progress). Settings named in ``keep`` (set explicitly by the user) and the learned kernel's
    explicit ``freeze_iters`` stay as given. Learning rates are left to
    :func:`boost_short_run_lrs`.
    """
    t = cfg.train
    if t.time_budget is not None or t.iters >= FULL_ITERS:
        return {}
    s = t.iters / FULL_ITERS
    scaled = {}
    for key, (full, lo) in RUN_LENGTH_SCHEDULES.items():
        if key not in keep:
            setattr(t, key, max(lo, round(full * s)))
            scaled[key] = getattr(t, key)
    if "noise_lr" not in keep:
        # from the 30k default, not the current value, so scaling twice changes nothing
        t.noise_lr = scaled["noise_lr"] = TrainConfig.noise_lr * min(NOISE_LR_MULT_MAX, 1 / s)
    if cfg.kernel == "learned" and "freeze_iters" not in cfg.kernel_options:
        cfg.kernel_options["freeze_iters"] = scaled["freeze_iters"] = round(LEARNED_FREEZE_ITERS * s)
    return scaled


#: short runs raise the log-scale LR by sqrt(30k / iters), at most this much
SCALES_LR_MULT_MAX = 10.0
#: ... and the learned kernel's latent and network LRs by 30k / iters, at most this much
KERNEL_LR_MULT_MAX = 10.0
#: the learned kernels' latent: (option name, default LR) per primitive type
#: (kernels/learned.py z3d_lr, kernels/learned_planar.py z_lr)
LEARNED_LATENT_LR = {"volumetric": ("z3d_lr", 1e-4), "planar": ("z_lr", 1e-4)}


def boost_short_run_lrs(cfg: "FitConfig", keep: frozenset | set = frozenset()) -> dict:
    """Raise the learning rates tuned for 30k iterations on a shorter run; returns what changed.

    ``splatk fit`` and ``splatk bench`` do this for every short run unless told not to
    (``--no-short-run-lrs``, ``short_run_lrs: false`` as in the demo preset): 2000 iterations,
    50k Gaussians, fox at 1/16: 23.79 dB without, 29.77 with; lego at 1/8: 31.60 without, 31.22
    with. It was bench-only until the trainer's collapse checks kept LR x10 on top of it above
    the initial PSNR in the stability matrix (docs/measurements.md, "Stability"). Settings named in ``keep``
    and explicit kernel options stay as given.
    """
    t = cfg.train
    if t.time_budget is not None or t.iters >= FULL_ITERS:
        return {}
    s = t.iters / FULL_ITERS
    boosted = {}
    if "scales_lr_mult" not in keep:
        # the log-scale LR is tuned for 30k iterations; short runs starve it (fox, random
        # init, 2000 iterations: learned k=4 13.9 -> 21.7 dB at x3, gaussian 20.9 -> 21.6)
        t.scales_lr_mult = boosted["scales_lr_mult"] = round(min(SCALES_LR_MULT_MAX, math.sqrt(1 / s)), 3)
    if cfg.kernel == "learned":
        # the latents and networks get 30k / iters fewer steps, and their LRs decay over the
        # shorter run: raise them by that factor, at most x10 (cup / fox at 1/8, 2000
        # iterations, learned k=4: z3d and network LR x10 gave +0.97 / +0.39 dB). The planar
        # kernel has the same schedule options, its latent LR is called z_lr.
        boost = min(KERNEL_LR_MULT_MAX, 1 / s)
        opts = cfg.kernel_options
        latent_key, latent_lr = LEARNED_LATENT_LR[cfg.primitive]
        if latent_key not in opts:
            opts[latent_key] = boosted[latent_key] = latent_lr * boost
        if "net_lr_mult" not in opts:
            pretrained = str(opts.get("weights", "default")).lower() != "none"
            # without pretraining the paper's x10 already applies; do not stack the two
            base = 1.0 if pretrained else 10.0
            opts["net_lr_mult"] = boosted["net_lr_mult"] = max(base, round(boost, 3))
    return boosted


def load_resume_state(out: Path) -> tuple[str, "FitConfig", dict]:
    """(scene path, settings, checkpoint) of the run in ``out``; InputError if any is unusable."""
    from ..torch_files import load_torch_file

    out = Path(out)
    ckpt_path = out / "checkpoints" / "last.pt"
    if not ckpt_path.is_file():
        raise InputError(out, "no checkpoint to resume from (checkpoints/last.pt is missing)",
                         "run without --resume")
    cfg_path = out / "config.yaml"
    try:
        saved = yaml.safe_load(cfg_path.read_text())
        scene_path = saved["scene"]
        cfg = FitConfig.from_dict(saved["settings"])
    except FileNotFoundError:
        raise InputError(cfg_path, "run settings are missing", "run without --resume") from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise InputError(cfg_path, f"run settings cannot be read ({type(e).__name__}: {e})",
                         "restore the file or run without --resume") from None
    try:
        state = load_torch_file(ckpt_path, "start the run again without --resume", map_location=cfg.device)
        if not isinstance(state, dict) or "trainer" not in state:
            raise ValueError("not a splatk checkpoint")
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - truncated zip, unpickling error, wrong file ...
        msg = str(e).strip().splitlines()[0][:120] if str(e).strip() else type(e).__name__
        raise InputError(ckpt_path, f"checkpoint is corrupt or truncated ({msg})",
                         "delete the run folder and start again without --resume") from None
    return scene_path, cfg, state


def build_model(scene, cfg: FitConfig, budget: int | None = None) -> SplatModel | PlanarModel:
    """Initial model; ``budget`` (default ``cfg.train.budget``) caps the initial points."""
    if cfg.primitive not in PRIMITIVES:
        raise InputError(None, f"unknown primitive type {cfg.primitive!r}",
                         f"use --primitive {' or '.join(PRIMITIVES)}")
    if cfg.primitive == "planar":
        # checked before the points are made: an unknown (primitive, kernel) pair is an input
        # error with a message, not a traceback
        make_kernel(cfg.kernel, "planar", **cfg.kernel_options)
    budget = cfg.train.budget if budget is None else budget
    if cfg.train.init == "auto":  # recorded resolved, so config.yaml says what ran
        cfg.train.init = "sfm" if scene.points.shape[0] > 0 else "random"
    n_random = cfg.train.random_points
    if n_random is None:
        # a quarter of the budget, for MCMC to grow (TrainConfig.random_points); --budget auto
        # starts full, since each of its stages compares models that filled their budgets
        n_random = budget if cfg.auto_budget is not None else max(1, budget // 4)
    pts, cols = initial_points(scene, cfg.train.init, budget, n_random, cfg.train.seed)
    # Random points start 10x smaller than their neighbour spacing (3DGS-MCMC's init_scale 0.1):
    # at full spacing they blanket every view and take thousands of iterations to clear.
    # That 0.1 is for a 3-sigma Gaussian support; kernels whose support ends at 1 sigma (Beta,
    # learned) start 3x larger so that every kernel starts from the same screen footprint.
    # Measured on cup (downscale 4, 20k random points, 1000 iterations, train-view PSNR):
    # learned k=2 20.05 dB at 0.1, 22.06 dB at 0.3; Gaussian 21.44 dB at 0.1.
    # Planar kernels both end at the 3-sigma disk, as the Gaussian.
    if cfg.train.init_scale > 0:
        scale_factor = cfg.train.init_scale
    elif cfg.train.init == "random":
        support = getattr(KERNELS.get((cfg.primitive, cfg.kernel)), "support_sigmas", GAUSSIAN_SUPPORT_SIGMAS)
        scale_factor = 0.1 * GAUSSIAN_SUPPORT_SIGMAS / support
    else:
        scale_factor = 1.0
    model_class = PlanarModel if cfg.primitive == "planar" else SplatModel
    return model_class.from_points(pts, cols, kernel=cfg.kernel, color=cfg.color, scale_factor=scale_factor,
                                  kernel_options=cfg.kernel_options, color_options=_color_options(cfg))


def run_fit(
    scene_path: str | Path | None,
    out: str | Path,
    cfg: FitConfig | None = None,
    overwrite: bool = False,
    resume: bool = False,
    config_sources: dict | None = None,
    on_start: Callable[[dict], None] | None = None,
    on_step: Callable[[StepInfo], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    resume_options: dict | None = None,
) -> Path:
    """Train and write RUN/model.pt; returns the run folder.

    Every setting is checked, and the scene loaded and checked, before the run folder is
    touched; ``overwrite`` replaces only a run folder splatk wrote (``splatk.outputs``), and the
    folder is locked while this process writes it.

    With ``resume``, the settings saved in RUN/config.yaml are used and training continues
    from RUN/checkpoints/last.pt (parameters, optimiser, RNGs, density control). ``scene_path``
    may be None; given, it must be the run's scene. ``resume_options`` (flat option names, as
    :func:`fit_config_from_options` takes them) are what the user asked for on resume: those in
    :data:`RESUME_CHANGEABLE` are applied and recorded, any other must equal the run's value.
    The scene must still be the one the run started from (its fingerprint is checked).

    Raises :class:`~splatk.errors.TrainingStalled` when training cannot get past a point (see
    :class:`~splatk.train.trainer.Trainer`); the checkpoint then holds the last healthy state.
    """
    out = Path(out)
    if resume:
        with OutputDir(out, RUN_KIND, keep=True):
            saved_scene, cfg, state = load_resume_state(out)
            if scene_path is not None and Path(scene_path).resolve() != Path(saved_scene).resolve():
                raise InputError(scene_path, f"is not the scene of the run in {out} ({saved_scene})",
                                 "resume without SCENE, or start a new run with another --out")
            cfg, changes = _apply_resume_options(out, cfg, resume_options or {})
            check_fit_config(cfg, f"run's {out / 'config.yaml'}")
            return _fit(saved_scene, out, cfg, state, changes, config_sources, on_start, on_step, should_stop)
    if cfg is None:
        cfg = FitConfig()
    check_fit_config(cfg, config_sources)
    if scene_path is None:
        raise InputError(None, "no scene given", "pass the scene folder (or --resume to continue a run)")
    check_output_dir(out, RUN_KIND, overwrite, inputs=[scene_path])  # refuse before any work
    return _fit(scene_path, out, cfg, None, {}, config_sources, on_start, on_step, should_stop,
                overwrite=overwrite)


def _apply_resume_options(out: Path, saved: FitConfig, given: dict) -> tuple[FitConfig, dict]:
    """The run's settings with the options given on resume applied; InputError for one that
    would change what the run is (kernel, budget, ...). Returns (config, {setting: new value})."""
    given = {k: v for k, v in given.items() if v is not None}
    if not given:
        return saved, {}
    cfg, _ = fit_config_from_options(given, base=saved)
    before, after = _flatten(saved.to_dict()), _flatten(cfg.to_dict())
    changed = {k: after.get(k) for k in sorted(set(before) | set(after)) if before.get(k) != after.get(k)}
    changeable = {k for k in changed if k.split(".")[-1] in RESUME_CHANGEABLE}
    refused = [k for k in changed if k not in changeable]
    if refused:
        k = refused[0]
        raise InputError(out / "config.yaml", f"resume would change {k} from {before.get(k)!r} to {after.get(k)!r}",
                         "resume continues the run as it was started: drop that option, or start a new run "
                         "with another --out")
    return cfg, {k: changed[k] for k in changeable}


def _flatten(d: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in d.items():
        if isinstance(v, dict) and k != "background":
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def scene_fingerprint(scene) -> str:
    """A hash of what training reads from the scene: every view's name, size, intrinsics, pose
    and pixels, and the SfM points."""
    h = hashlib.sha256()
    for cam in scene.train + scene.test:
        h.update(f"{cam.name}|{cam.width}|{cam.height}|{cam.fx}|{cam.fy}|{cam.cx}|{cam.cy}".encode())
        h.update(cam.world_to_cam.contiguous().numpy().tobytes())
        if cam.image is not None:
            h.update(cam.image.contiguous().numpy().tobytes())
    h.update(scene.points.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _load_checked_scene(scene_path, cfg: FitConfig):
    resolve_device(cfg.train.device, cfg.train.backend)  # what the trainer will use
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    scene = load_scene(scene_path, downscale=cfg.downscale, test_every=cfg.test_every,
                       background=tuple(cfg.background) if cfg.background else None)
    if cfg.view_stride > 1:
        scene.train = scene.train[::cfg.view_stride]
    if len(scene.train) == 0:
        raise InputError(scene_path, "no training images found")
    return scene


def _fit(scene_path, out: Path, cfg: FitConfig, state: dict | None, resume_changes: dict,
         config_sources, on_start, on_step, should_stop, overwrite: bool = False) -> Path:
    """The fit itself, once the settings are checked: ``state`` is the checkpoint to resume."""
    resume = state is not None
    scene = _load_checked_scene(scene_path, cfg)
    fingerprint = scene_fingerprint(scene)
    if resume:
        saved_print = (state.get("meta") or {}).get("scene_fingerprint")
        if saved_print is not None and saved_print != fingerprint:
            raise InputError(scene_path, "the scene changed since the run started (its images, cameras or points "
                             "differ from the checkpoint's)", "restore the scene, or start a new run with another --out")
    auto, holdout = None, []
    all_train = list(scene.train)  # the refit of --budget auto trains on every one, in this order
    if cfg.auto_budget is not None:
        try:
            scene.train, holdout = split_holdout(scene.train, cfg.auto_budget.holdout_every)
        except ValueError as e:
            raise InputError(scene_path, str(e), "use a number for --budget") from None
        auto = AutoBudget(cfg.auto_budget, cfg.train.budget, cfg.train.refine_stop)
    selection_train = list(scene.train)  # --budget auto's optimiser views while choosing
    if resume and auto is not None and state.get("auto_budget") is not None:
        auto.load_state_dict(state["auto_budget"])
    if auto is not None and auto.refitting:  # resuming the refit: a fixed run at the chosen budget
        trainer = _refit_trainer(scene, all_train, cfg, auto.chosen)
    elif auto is not None and auto.current_short is not None:  # resuming a short selection run
        trainer = _short_run_trainer(scene, selection_train, cfg, auto.current_short)
    else:
        torch.manual_seed(cfg.train.seed)  # model construction may draw (e.g. spherical-Beta lobes)
        model = build_model(scene, cfg, budget=auto.start_budget if auto is not None else None)
        trainer = Trainer(scene, model, cfg.train)
    if resume:
        if auto is not None and auto.holdout_returned and not auto.refitting and auto.current_short is None:
            # the optimiser's view list (and its queue) included them
            auto.return_holdout(trainer, holdout)
        trainer.load_state_dict(state["trainer"])
        initial_psnr = state.get("initial_psnr")
        del state
        _clean_resume_leftovers(out, trainer.it)
        if resume_changes:
            _record_resume_changes(out, cfg, resume_changes, trainer.it)
        return _train(scene_path, out, cfg, scene, fingerprint, trainer, auto, holdout, all_train,
                      selection_train, initial_psnr, resume, on_start, on_step, should_stop)
    with OutputDir(out, RUN_KIND, overwrite, inputs=[scene_path]):
        _write_config(out, scene_path, cfg, config_sources or {})
        initial_psnr = render_psnr(trainer.model, scene.test, scene.background, trainer.backend)
        return _train(scene_path, out, cfg, scene, fingerprint, trainer, auto, holdout, all_train,
                      selection_train, initial_psnr, resume, on_start, on_step, should_stop)


def _train(scene_path, out: Path, cfg: FitConfig, scene, fingerprint: str, trainer: Trainer, auto, holdout,
           all_train, selection_train, initial_psnr, resume: bool, on_start, on_step, should_stop) -> Path:
    ckpt_path = out / "checkpoints" / "last.pt"
    spec = model_spec(trainer.model, cfg.kernel_options, _color_options(cfg))
    meta = {
        "scene": str(Path(scene_path).resolve()),
        "downscale": cfg.downscale,
        "test_every": cfg.test_every,
        "background": list(scene.background),
        "primitive": cfg.primitive,
        "scene_fingerprint": fingerprint,
    }
    if on_start:
        on_start({"scene": scene, "model": trainer.model, "iters": cfg.train.iters,
                  "start_it": trainer.it, "backend": cfg.train.backend, "config": cfg})

    saved_it = {"it": trainer.it if resume else None}
    # the trainer whose model is saved: --budget auto's refit replaces the selection's
    current = {"trainer": trainer, "initial_psnr": initial_psnr}

    def checkpoint(tr: Trainer) -> None:
        state = {"trainer": tr.state_dict(), "spec": spec, "meta": meta,
                 "initial_psnr": current["initial_psnr"],
                 "auto_budget": auto.state_dict() if auto is not None else None}
        _save(lambda: atomic_torch_save(state, ckpt_path), ckpt_path, out, saved_it["it"])
        saved_it["it"] = tr.it

    log = open(out / "train_log.jsonl", "a")

    def step(info: StepInfo) -> None:
        if info.it % 100 == 0 or info.event:
            log.write(json.dumps({"it": info.it, "loss": info.loss, "psnr": info.psnr,
                                  "num": info.num_primitives, "elapsed": round(info.elapsed, 3),
                                  "event": info.event}) + "\n")
            log.flush()
        if on_step:
            on_step(info)

    wall0 = time.time()
    interrupted = False
    def make_refit_trainer(budget: int) -> Trainer:
        tr = _refit_trainer(scene, all_train, cfg, budget)
        # the final model descends from this one, so its PSNR is the run's initial PSNR
        current["trainer"] = tr
        current["initial_psnr"] = render_psnr(tr.model, scene.test, scene.background, tr.backend)
        return tr

    def make_short_trainer(budget: int) -> Trainer:
        current["trainer"] = _short_run_trainer(scene, selection_train, cfg, budget)
        return current["trainer"]

    try:
        try:
            if auto is not None:
                auto.run(trainer, holdout, step, should_stop, checkpoint, cfg.checkpoint_every,
                         make_refit_trainer=make_refit_trainer,
                         make_short_trainer=make_short_trainer)
            else:
                trainer.run(step, should_stop, checkpoint, cfg.checkpoint_every)
        except KeyboardInterrupt:
            interrupted = True
        except TrainingStalled as stalled:
            # keep the last healthy state, not the one that could not get past this point
            current["trainer"].restore_last_healthy()
            checkpoint(current["trainer"])
            raise stalled.at(out)
        trainer = current["trainer"]
        checkpoint(trainer)
    finally:
        log.close()
    if interrupted:
        raise KeyboardInterrupt
    _save(lambda: save_model(trainer.model, out / "model.pt", spec, meta), out / "model.pt", out, saved_it["it"])
    train_seconds = trainer.elapsed
    if auto is not None and auto.refitting:  # the selection is part of what the run cost
        train_seconds += auto.selection_seconds or 0.0
    summary = {
        "iterations": trainer.it,
        "train_seconds": round(train_seconds, 2),
        "wall_seconds_this_session": round(time.time() - wall0, 2),
        "num_primitives": trainer.model.num_primitives,
        "footprint_mb": trainer.model.footprint_bytes() / 2**20,
        "kernel": cfg.kernel,
        "primitive": cfg.primitive,
        "color": cfg.color,
        "backend": cfg.train.backend,
        "events": trainer.events,
        "initial_psnr": current["initial_psnr"],
        "view_stride": cfg.view_stride,
        "train_views": len(trainer.scene.train),
    }
    if auto is not None:
        summary["auto_budget"] = auto.report(holdout)
    (out / "fit.json").write_text(json.dumps(summary, indent=2))
    return out


def _fixed_trainer(scene, views: list, cfg: FitConfig, **train: object) -> Trainer:
    """The trainer `splatk fit --budget N` builds (same seed, init rule and schedules), on
    ``views``, with ``train`` replacing TrainConfig fields: --budget auto's refit and short runs."""
    fixed = replace(cfg, auto_budget=None, train=replace(cfg.train, **train))
    scene.train = list(views)
    torch.manual_seed(fixed.train.seed)
    return Trainer(scene, build_model(scene, fixed), fixed.train)


def _refit_trainer(scene, all_train: list, cfg: FitConfig, budget: int) -> Trainer:
    """--budget auto's refit: a fixed-budget run at ``budget`` on every train view."""
    return _fixed_trainer(scene, all_train, cfg, budget=budget)


def _short_run_trainer(scene, views: list, cfg: FitConfig, budget: int) -> Trainer:
    """--budget auto's short selection run at ``budget``: a fixed-budget run on ``views`` (the
    held-out ones left out) for ``stage_share`` of the iterations (or of the time budget), its
    progress-based schedules complete, MCMC refining often enough to reach the budget from the
    init in the first half of it."""
    t, share = cfg.train, cfg.auto_budget.stage_share
    iters = t.iters if t.time_budget else max(1, round(share * t.iters))
    time_budget = share * t.time_budget if t.time_budget else None
    refine_every = t.refine_every
    if not t.time_budget:
        growth_steps = math.ceil(math.log(4.0) / math.log(MCMCConfig.growth))  # a quarter -> all
        refine_every = max(1, min(refine_every, int(iters / 2 / growth_steps)))
    return _fixed_trainer(scene, views, cfg, budget=budget, iters=iters, time_budget=time_budget,
                          refine_every=refine_every)


def _save(write: Callable[[], object], path: Path, out: Path, kept_it: int | None) -> None:
    """Run an atomic write; a full disk or a permission problem becomes an InputError.

    The atomic write leaves the previous file in place, so the message can say what survives.
    """
    try:
        write()
    except OSError as e:
        kept = (f"the checkpoint of iteration {kept_it} is intact; " if kept_it is not None else "")
        raise InputError(path, f"cannot write ({e.strerror or e})",
                         f"free disk space or fix permissions; {kept}continue with `splatk fit --resume "
                         f"--out {out}`") from None


def _clean_resume_leftovers(out: Path, it: int) -> None:
    """Before continuing at iteration ``it``: drop temp files of a write that was killed and the
    log lines written after the checkpoint (they are about to be written again)."""
    for tmp in (out / "checkpoints").glob("*.tmp"):
        tmp.unlink(missing_ok=True)
    for tmp in out.glob("model.pt.*.tmp"):
        tmp.unlink(missing_ok=True)
    log = out / "train_log.jsonl"
    if log.is_file():
        keep = []
        for line in log.read_text().splitlines():
            try:
                if json.loads(line)["it"] <= it:
                    keep.append(line)
            except (ValueError, KeyError, TypeError):
                continue  # a line cut off by the kill
        log.write_text("".join(x + "\n" for x in keep))


def _record_resume_changes(out: Path, cfg: FitConfig, changes: dict, it: int) -> None:
    """config.yaml takes the settings a resume changed, and says so beside each."""
    path = out / "config.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["settings"] = cfg.to_dict()
    for key, value in changes.items():
        doc.setdefault("sources", {})[key.split(".")[-1]] = f"changed on resume at iteration {it}: {value}"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def _write_config(out: Path, scene_path, cfg: FitConfig, sources: dict) -> None:
    doc = {
        "scene": str(Path(scene_path).resolve()),
        "settings": cfg.to_dict(),
        "sources": sources,
    }
    (out / "config.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
