"""Runs shorter than the paper's 30k iterations: the step-count schedules and the learning rates
tuned for 30k, scaled to the run's length.

:func:`scale_to_run_length` is the one step the fit's settings go through
(:func:`~splatk.stages.fit_config.fit_config_from_options` applies it to every new run, so
`splatk fit`, `splatk bench` and a Python caller train alike); ``FitConfig.scale_schedules`` and
``FitConfig.short_run_lrs`` switch its two parts, and config.yaml records both. A kernel scales
its own options (:meth:`~splatk.kernels.base.Kernel.scale_to_run`).
"""
from __future__ import annotations

import math

from ..train.mcmc import MCMCConfig

#: the paper's run length; the step-count schedules below are tuned for it
FULL_ITERS = 30_000
#: step-count schedules at 30k iterations: (value, smallest value when scaled to a shorter run)
RUN_LENGTH_SCHEDULES = {"refine_start": (500, 0), "refine_every": (100, 5), "sh_degree_interval": (1000, 1),
                        "normal_from": (7000, 0), "distortion_from": (3000, 0)}
#: the RUN_LENGTH_SCHEDULES that are TrainConfig fields (the others are MCMC's)
TRAIN_SCHEDULES = ("sh_degree_interval", "normal_from", "distortion_from")
#: ADC's step-count schedules at 30k iterations (3DGS): (value, smallest value when scaled)
ADC_SCHEDULES = {"densify_from": (500, 0), "densify_until": (15_000, 1), "densify_every": (100, 5),
                 "opacity_reset_every": (3000, 10)}
#: short runs raise MCMC's position noise (DBS's noise_lr, tuned for 30k iterations) by
#: 30k / iters, at most this much
NOISE_LR_MULT_MAX = 10.0
#: short runs raise the log-scale LR by sqrt(30k / iters), at most this much
SCALES_LR_MULT_MAX = 10.0


def run_fraction(cfg) -> float | None:
    """(``cfg``: a :class:`~splatk.stages.fit_config.FitConfig`, as below) iters / 30k for a run shorter than 30k iterations; None when nothing scales (a full
    run, or a time budget: those schedules follow progress)."""
    t = cfg.train
    if t.time_budget is not None or t.iters >= FULL_ITERS:
        return None
    return t.iters / FULL_ITERS


def _kernel_class(cfg):
    from ..kernels import KERNELS

    return KERNELS.get((cfg.primitive, cfg.kernel))


def _scale_kernel_options(cfg, s: float, keep, schedules: bool) -> dict:
    """The kernel's own scaling (:meth:`~splatk.kernels.base.Kernel.scale_to_run`) of its
    schedules, or else of its learning rates, applied to ``cfg.kernel_options``."""
    kernel = _kernel_class(cfg)
    if kernel is None:
        return {}
    changes = kernel.scale_to_run(cfg.kernel_options, s, keep, schedules=schedules, lrs=not schedules)
    cfg.kernel_options.update(changes)
    return changes


def scale_schedules_to_run(cfg, keep: frozenset | set = frozenset()) -> dict:
    """Shrink the step-count schedules of a run shorter than 30k iterations in proportion
    (gsplat's ``steps_scaler`` idea); returns {setting: new value} (empty when nothing changed).

    Unscaled, a 2000-iteration run would refine only every 100 steps, so MCMC's 5% growth per
    refine could not reach the budget (a quarter-budget random init ends near 43% of it), raise
    the SH degree twice, and leave a learned kernel's networks frozen for the whole run.
    MCMC's position noise grows by 30k / iters (at most x10): the means get that many fewer
    gradient steps, and the noise is what moves near-transparent primitives to where they are
    needed (docs/decisions/0002-mcmc-noise-short-runs.md). Settings named in ``keep`` (set explicitly by the user) and
    explicit kernel options stay as given. Learning rates are left to :func:`boost_short_run_lrs`.
    """
    s = run_fraction(cfg)
    if s is None:
        return {}
    t = cfg.train
    scaled = {}
    for key, (full, lo) in RUN_LENGTH_SCHEDULES.items():
        if key not in keep:
            target = t if key in TRAIN_SCHEDULES else t.mcmc
            setattr(target, key, max(lo, round(full * s)))
            scaled[key] = getattr(target, key)
    if t.strategy == "adc":
        for key, (full, lo) in ADC_SCHEDULES.items():
            if key not in keep:
                setattr(t.adc, key, max(lo, round(full * s)))
                scaled[key] = getattr(t.adc, key)
    if "noise_lr" not in keep:
        # from the 30k default, not the current value, so scaling twice changes nothing
        t.mcmc.noise_lr = scaled["noise_lr"] = MCMCConfig.noise_lr * min(NOISE_LR_MULT_MAX, 1 / s)
    scaled.update(_scale_kernel_options(cfg, s, keep, schedules=True))
    return scaled


def boost_short_run_lrs(cfg, keep: frozenset | set = frozenset()) -> dict:
    """Raise the learning rates tuned for 30k iterations on a shorter run; returns what changed.

    On for every short run unless told not to (``--no-short-run-lrs``, ``short_run_lrs: false``
    as in the demo preset; docs/decisions/0001-short-run-scaling.md has what it gains and costs).
    The trainer's collapse checks keep LR x10 on top of it above the initial PSNR in the
    stability matrix (docs/decisions/0005-collapse-rollback.md). Settings named in ``keep`` and
    explicit kernel options stay as given.
    """
    s = run_fraction(cfg)
    if s is None:
        return {}
    boosted = {}
    if "scales_lr_mult" not in keep:
        # the log-scale LR is tuned for 30k iterations; short runs starve it (decision 0001)
        cfg.train.scales_lr_mult = boosted["scales_lr_mult"] = round(min(SCALES_LR_MULT_MAX, math.sqrt(1 / s)), 3)
    boosted.update(_scale_kernel_options(cfg, s, keep, schedules=False))
    return boosted


def scale_to_run_length(cfg, keep: frozenset | set = frozenset()) -> dict:
    """Both steps, as ``cfg.scale_schedules`` and ``cfg.short_run_lrs`` say (the LRs only with
    the schedules); returns {setting: new value}."""
    if not cfg.scale_schedules:
        return {}
    changed = scale_schedules_to_run(cfg, keep)
    if cfg.short_run_lrs:
        changed.update(boost_short_run_lrs(cfg, keep))
    return changed
