"""`splatk fit`: scene folder -> trained model in a run folder (layout:
:mod:`splatk.stages.run_folder`).

:func:`run_fit` checks the settings and the scene, then trains: one :class:`Trainer`, or with
``--budget auto`` the short runs, the refit and the compaction (:mod:`splatk.stages.autobudget`).
The settings come as a :class:`FitConfig`; :func:`~splatk.stages.fit_config.fit_config_from_options`
builds one from flat options as `splatk fit` and `splatk bench` do (short runs scaled to their
length included), so a Python caller that goes through it trains as the command does.
"""
from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import torch
import yaml

from ..data import load_scene
from ..errors import InputError, TrainingStalled
from ..backends import GAUSSIAN_SUPPORT_SIGMAS
from ..device import resolve_device
from ..kernels import KERNELS, make_kernel
from ..kernels.auto_k import resolve_auto_k, source_text as auto_k_source
from ..machine import machine_info
from ..models.init import initial_points
from ..models.io import model_spec
from ..models.planar import PlanarModel
from ..models.volumetric import SplatModel
from ..outputs import OutputDir, check_output_dir
from ..train.distributed import SINGLE, World, join, launched_world, leave, local_device
from ..train.trainer import StepInfo, Trainer
from ..yaml_files import describe_yaml_error
from .auto_settings import resolve_init, train_pixels_per_view
from .autobudget import AutoBudget, render_psnr, split_holdout
from .fit_config import PRIMITIVES, FitConfig, check_fit_config, fit_config_from_options
from .fit_memory import color_options as _color_options
from .fit_ranks import Start, agree, receive, settings_mismatch
from .run_folder import RunFolder, clean_resume_leftovers, record_resume_changes, write_config

#: the marker kind of a run folder (``splatk.outputs``)
RUN_KIND = "fit run"
#: settings ``fit --resume`` may change; every other one given on resume must equal the run's
RESUME_CHANGEABLE = ("iters", "time_budget", "checkpoint_every", "threads", "backend", "device", "nproc")


@dataclass
class FitResult:
    """What :func:`run_fit` wrote: the run folder and the summary it holds as RUN/fit.json."""

    path: Path
    summary: dict


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
        why = describe_yaml_error(e) if isinstance(e, yaml.YAMLError) else f"{type(e).__name__}: {e}"
        raise InputError(cfg_path, f"run settings cannot be read ({why})",
                         "restore the file or run without --resume") from None
    try:
        # onto the CPU whatever device wrote it: the trainer moves each part to the device the
        # run goes on with (--device may change on resume)
        state = load_torch_file(ckpt_path, "start the run again without --resume", map_location="cpu")
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
    resolve_init(cfg, scene)
    n_random = cfg.train.random_points
    if n_random is None:
        # a quarter of the budget, for MCMC to grow (TrainConfig.random_points); --budget auto
        # starts full, since each of its stages compares models that filled their budgets
        n_random = budget if cfg.auto_budget is not None else max(1, budget // 4)
    pts, cols = initial_points(scene, cfg.train.init, budget, n_random, cfg.train.seed, cfg.train.random_extent)
    # Random points start 10x smaller than their neighbour spacing (3DGS-MCMC's init_scale 0.1):
    # at full spacing they blanket every view and take thousands of iterations to clear.
    # That 0.1 is for a 3-sigma Gaussian support; kernels whose support ends at 1 sigma (Beta,
    # learned) start 3x larger so that every kernel starts from the same screen footprint.
    # (decision 0007 has the measurement.)
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
                                  init_opacity=cfg.train.init_opacity, kernel_options=cfg.kernel_options,
                                  color_options=_color_options(cfg))


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
) -> FitResult:
    """Train and write RUN/model.pt; returns the run folder and its summary (RUN/fit.json).

    ``cfg`` is trained as given; :func:`fit_config_from_options` builds it from flat options
    as `splatk fit` does, the run-length scaling of a short run included.

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

    In a process that a launcher started as one rank of a data-parallel job (``RANK``,
    ``WORLD_SIZE``, ... in the environment: torchrun, or ``splatk fit --nproc``), the fit joins
    the job: rank 0 does all of the above and every other rank trains beside it from rank 0's
    start (:mod:`splatk.stages.fit_ranks`), writing nothing. A rank that loses its peers
    raises :class:`~splatk.train.distributed.WorkerLost`.
    """
    out = Path(out)
    world = launched_world()
    if not world.distributed:
        return _run_fit(scene_path, out, cfg, overwrite, resume, config_sources, on_start, on_step, should_stop,
                        resume_options, SINGLE, None)
    join(world)
    if cfg is not None:
        cfg.device = cfg.train.device = local_device(cfg.device, world)
    if not world.main:
        result = _follow(world, out, cfg, resume, on_start, on_step, should_stop)
    else:
        start = Start(world)
        try:
            result = _run_fit(scene_path, out, cfg, overwrite, resume, config_sources, on_start, on_step,
                              should_stop, resume_options, world, start)
        except InputError as e:
            start.fail(e.message())
            raise
    # only after a fit that every rank finished: tearing the group down while a peer is gone
    # can hang or abort, and a process that failed exits anyway
    leave()
    return result


def _run_fit(scene_path, out: Path, cfg, overwrite, resume, config_sources, on_start, on_step, should_stop,
             resume_options, world: World, start: Start | None) -> FitResult:
    if resume:
        with OutputDir(out, RUN_KIND, keep=True):
            saved_scene, cfg, state = load_resume_state(out)
            if scene_path is not None and Path(scene_path).resolve() != Path(saved_scene).resolve():
                raise InputError(scene_path, f"is not the scene of the run in {out} ({saved_scene})",
                                 "resume without SCENE, or start a new run with another --out")
            given = dict(resume_options or {})
            if cfg.nproc != world.size:  # the run goes on with the processes it has now
                given.setdefault("nproc", world.size)
            cfg, changes = _apply_resume_options(out, cfg, given)
            check_fit_config(cfg, f"run's {out / 'config.yaml'}")
            if world.distributed:
                cfg.device = cfg.train.device = local_device(cfg.device, world)
            return _fit(saved_scene, out, cfg, state, changes, config_sources, on_start, on_step, should_stop,
                        world=world, start=start)
    if cfg is None:
        cfg = FitConfig()
    check_fit_config(cfg, config_sources)
    if scene_path is None:
        raise InputError(None, "no scene given", "pass the scene folder (or --resume to continue a run)")
    check_output_dir(out, RUN_KIND, overwrite, inputs=[scene_path], resumable=True)  # refuse before any work
    return _fit(scene_path, out, cfg, None, {}, config_sources, on_start, on_step, should_stop,
                overwrite=overwrite, world=world, start=start)


def _follow(world: World, out: Path, cfg: FitConfig | None, resume: bool, on_start, on_step,
            should_stop) -> FitResult:
    """A rank other than 0: check this process's settings and scene against rank 0's start,
    then train beside it from rank 0's state; nothing is written."""
    start = receive(world)
    problem, trainer = None, None
    try:
        run_cfg = FitConfig.from_dict(start["settings"])
        if cfg is not None:
            if not resume:
                problem = settings_mismatch(cfg.to_dict(), start["settings"], world.rank)
            run_cfg.threads, run_cfg.device, run_cfg.train.device = cfg.threads, cfg.device, cfg.device
        scene = _load_checked_scene(start["scene"], run_cfg)
        if problem is None and scene_fingerprint(scene) != start["fingerprint"]:
            problem = (f"the scene {start['scene']} on rank {world.rank} differs from rank 0's (images, cameras "
                       "or points)")
        if problem is None:
            torch.manual_seed(run_cfg.train.seed)
            trainer = Trainer(scene, build_model(scene, run_cfg), run_cfg.train, world=world)
            trainer.load_state_dict(start["state"])
    except InputError as e:
        problem = f"rank {world.rank}: {e.message()}"
    del start
    agree(world, problem)
    if on_start:
        on_start({"scene": trainer.scene, "model": trainer.model, "iters": run_cfg.train.iters,
                  "start_it": trainer.it, "backend": run_cfg.train.backend, "config": run_cfg})
    trainer.run(on_step, lambda: world.any(bool(should_stop and should_stop())))
    return FitResult(Path(out), {"iterations": trainer.it, "rank": world.rank})


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
    """A hash of what training reads from the scene: every view's name, size, intrinsics, pose,
    pixels and mask, and the SfM points."""
    h = hashlib.sha256()
    for cam in scene.train + scene.test:
        h.update(f"{cam.name}|{cam.width}|{cam.height}|{cam.fx}|{cam.fy}|{cam.cx}|{cam.cy}".encode())
        h.update(cam.world_to_cam.contiguous().numpy().tobytes())
        if cam.image is not None:
            h.update(cam.image.contiguous().numpy().tobytes())
        if cam.mask is not None:  # a scene without masks keeps the fingerprint it had
            h.update(cam.mask.contiguous().numpy().tobytes())
    h.update(scene.points.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _load_checked_scene(scene_path, cfg: FitConfig):
    resolve_device(cfg.train.device, cfg.train.backend)  # what the trainer will use
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    scene = load_scene(scene_path, downscale=cfg.downscale, test_every=cfg.test_every,
                       background=tuple(cfg.background) if cfg.background else None, eval_split=cfg.eval_split)
    if cfg.view_stride > 1:
        scene.train = scene.train[::cfg.view_stride]
    if len(scene.train) == 0:
        raise InputError(scene_path, "no training images found")
    return scene


def _fit(scene_path, out: Path, cfg: FitConfig, state: dict | None, resume_changes: dict,
         config_sources, on_start, on_step, should_stop, overwrite: bool = False, world: World = SINGLE,
         start: Start | None = None) -> FitResult:
    """The fit itself, once the settings are checked: ``state`` is the checkpoint to resume;
    ``start`` sends rank 0's start to the other ranks of a job."""
    resume = state is not None
    if start is not None:
        start.settings = cfg.to_dict()
    scene = _load_checked_scene(scene_path, cfg)
    fingerprint = scene_fingerprint(scene)
    if resume:
        saved_print = (state.get("meta") or {}).get("scene_fingerprint")
        if saved_print is not None and saved_print != fingerprint:
            raise InputError(scene_path, "the scene changed since the run started (its images, cameras, masks or "
                             "points differ from the checkpoint's)",
                             "restore the scene, or start a new run with another --out")
    if not resume:
        chosen = resolve_auto_k(cfg.kernel_options, train_pixels_per_view(scene.train), cfg.train.budget)
        if chosen is not None:
            config_sources = {**(config_sources or {}), "k": auto_k_source(chosen)}
    auto, holdout = None, []
    all_train = list(scene.train)  # the refit of --budget auto trains on every one, in this order
    if cfg.auto_budget is not None:
        try:
            scene.train, holdout = split_holdout(scene.train, cfg.auto_budget.holdout_every)
        except ValueError as e:
            raise InputError(scene_path, str(e), "use a number for --budget") from None
        auto = AutoBudget(cfg.auto_budget, cfg.train.budget, cfg.train.mcmc.refine_stop)
    fit = FitRun(scene, cfg, auto, holdout, all_train)
    fit.world, fit.start = world, start
    if resume and auto is not None and state.get("auto_budget") is not None:
        auto.load_state_dict(state["auto_budget"])
    if auto is not None and auto.refitting:  # resuming the refit: a fixed run at the chosen budget
        trainer = _refit_trainer(scene, all_train, cfg, auto.chosen)
    elif auto is not None and auto.current_short is not None:  # resuming a short selection run
        trainer = _short_run_trainer(scene, fit.selection_train, cfg, auto.current_short)
    else:
        torch.manual_seed(cfg.train.seed)  # model construction may draw (e.g. spherical-Beta lobes)
        model = build_model(scene, cfg, budget=auto.start_budget if auto is not None else None)
        trainer = Trainer(scene, model, cfg.train, world=world)
    fit.trainer = trainer
    if resume:
        trainer.load_state_dict(state["trainer"])
        fit.initial_psnr = state.get("initial_psnr")
        del state
        clean_resume_leftovers(out, trainer.it)
        if resume_changes:
            record_resume_changes(out, cfg.to_dict(), resume_changes, trainer.it)
        return fit.train(scene_path, out, fingerprint, resume, on_start, on_step, should_stop)
    with OutputDir(out, RUN_KIND, overwrite, inputs=[scene_path]):
        write_config(out, scene_path, cfg.to_dict(), config_sources or {})
        fit.initial_psnr = render_psnr(trainer.model, scene.test, scene.background, trainer.backend)
        return fit.train(scene_path, out, fingerprint, resume, on_start, on_step, should_stop)


class FitRun:
    """One fit in progress: the trainer whose model the run saves (``--budget auto``'s short
    runs and refit replace it), that model's initial test PSNR, the auto budget's state, and
    the run folder it writes (:class:`~splatk.stages.run_folder.RunFolder`)."""

    def __init__(self, scene, cfg: FitConfig, auto: AutoBudget | None, holdout: list, all_train: list):
        self.scene, self.cfg, self.auto = scene, cfg, auto
        self.holdout, self.all_train = holdout, all_train
        self.selection_train = list(scene.train)  # --budget auto's optimiser views while choosing
        self.trainer: Trainer | None = None
        self.initial_psnr: float | None = None
        self.folder: RunFolder | None = None
        self.world: World = SINGLE
        self.start: Start | None = None

    def checkpoint(self, tr: Trainer) -> None:
        self.folder.checkpoint(tr.it, {"trainer": tr.state_dict(), "initial_psnr": self.initial_psnr,
                                       "auto_budget": self.auto.state_dict() if self.auto is not None else None})

    def refit_trainer(self, budget: int) -> Trainer:
        """--budget auto's refit; the final model descends from it, so its PSNR is the run's
        initial PSNR."""
        self.trainer = tr = _refit_trainer(self.scene, self.all_train, self.cfg, budget)
        self.initial_psnr = render_psnr(tr.model, self.scene.test, self.scene.background, tr.backend)
        return tr

    def short_trainer(self, budget: int) -> Trainer:
        self.trainer = _short_run_trainer(self.scene, self.selection_train, self.cfg, budget)
        return self.trainer

    def train(self, scene_path, out: Path, fingerprint: str, resume: bool, on_start, on_step,
              should_stop) -> FitResult:
        cfg, scene, auto = self.cfg, self.scene, self.auto
        if self.start is not None:
            self.start.send(scene_path, fingerprint, self.trainer.state_dict())
        if self.world.distributed:  # every rank stops at the same iteration
            asked = should_stop
            should_stop = lambda: self.world.any(bool(asked and asked()))  # noqa: E731
        spec = model_spec(self.trainer.model, cfg.kernel_options, _color_options(cfg))
        meta = {
            "scene": str(Path(scene_path).resolve()),
            "downscale": cfg.downscale,
            "test_every": cfg.test_every,
            "eval_split": cfg.eval_split,
            "background": list(scene.background),
            "primitive": cfg.primitive,
            "scene_fingerprint": fingerprint,
        }
        if on_start:
            on_start({"scene": scene, "model": self.trainer.model, "iters": cfg.train.iters,
                      "start_it": self.trainer.it, "backend": cfg.train.backend, "config": cfg})
        self.folder = folder = RunFolder(out, spec, meta, saved_it=self.trainer.it if resume else None)

        def step(info: StepInfo) -> None:
            folder.log_step(info)
            if on_step:
                on_step(info)

        wall0 = time.time()
        interrupted = False
        try:
            try:
                if auto is not None:
                    auto.run(self.trainer, self.holdout, step, should_stop, self.checkpoint, cfg.checkpoint_every,
                             make_refit_trainer=self.refit_trainer, make_short_trainer=self.short_trainer)
                else:
                    self.trainer.run(step, should_stop, self.checkpoint, cfg.checkpoint_every)
            except KeyboardInterrupt:
                interrupted = True
            except TrainingStalled as stalled:
                # keep the last healthy state, not the one that could not get past this point
                self.trainer.restore_last_healthy()
                self.checkpoint(self.trainer)
                raise stalled.at(out)
            self.checkpoint(self.trainer)
        finally:
            folder.close_log()
        if interrupted:
            raise KeyboardInterrupt
        trainer = self.trainer
        folder.save_model(trainer.model, trainer.scene.train)
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
            "initial_psnr": self.initial_psnr,
            "view_stride": cfg.view_stride,
            "train_views": len(trainer.scene.train),
            "scene_warnings": list(scene.warnings),  # fields the loader read past (fit prints them too)
            # the CPU's vector units change float rounding, and a long run's result with it (the same
            # 30k cell on two CPUs: docs/results.md, stability), so a figure names its machine
            "machine": machine_info(),
        }
        if auto is not None:
            summary["auto_budget"] = auto.report(self.holdout)
        if self.world.distributed:
            summary["processes"] = self.world.size
            summary["gradient_bytes_per_step"] = trainer.sent_bytes  # the last step's all-reduce
        folder.write_summary(summary)
        return FitResult(out, summary)


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
    refine_every = t.mcmc.refine_every
    if not t.time_budget:
        growth_steps = math.ceil(math.log(4.0) / math.log(t.mcmc.growth))  # a quarter -> all
        refine_every = max(1, min(refine_every, int(iters / 2 / growth_steps)))
    return _fixed_trainer(scene, views, cfg, budget=budget, iters=iters, time_budget=time_budget,
                          mcmc=replace(t.mcmc, refine_every=refine_every))
