"""`splatk fit --budget auto`: choose the primitive budget from held-out train views.

Budgets are tried from ``start_fraction`` x the fit's budget upwards, doubling, judged by the
mean PSNR on train views held back from the optimiser (every ``holdout_every``-th train view;
the test views are never looked at). A doubling is kept while it gains more than
``threshold_db``.

By default (``selection: short_runs``) each budget gets one complete short run from the start:
``stage_share`` of the iterations with every schedule scaled to that length, judged at its end
against the previous budget's short run. On the four scenes of the issue (lego, fox, cup, bonsai
at 1/16, 2000 iterations, seeds 0 and 1, session 14) it chose fox 50k where the stages below
chose 200k / 100k on mid-run gains that did not last, bonsai 100k where they chose 50k, and lego
100k where they chose 50k (the compaction then cuts lego back below 50k). With the same
compaction, an auto run trained for 142-243 s against 279-1253 s with the stages (one thread,
two runs at a time, on the 2-core machines of sessions 14 and 13).

``selection: stages`` instead trains one run in stages, each for ``stage_share`` of the run; a
stage tries one doubling of the MCMC cap. The comparison is paired (``paired``, the default):
from the same start, the stage is trained twice with the same iterations and schedules, once at
the doubled cap ("grown") and once at the current one ("control"), and the gain is grown minus
control. Comparing the grown model with the one before the stage instead would also count the
stage's extra training as a gain of the primitives, and on short runs that alone exceeds any
sensible threshold, so the budget would never stop growing (what the unpaired rule,
``paired: false``, does). If the doubling gained more than ``threshold_db`` the grown model
trains on (warm start); otherwise the control model, already trained through the stage at the
chosen budget, does. The price is one extra stage of training per comparison, reported as
``comparison_seconds`` (under a time budget that time is not charged to the schedule). While
choosing, MCMC refines often enough for a doubling (15 growth steps of 5%) to fit in half a
stage. A stage judges a doubling right after it grew, which misleads: new primitives cost
held-out PSNR for hundreds of iterations (cup's 50k -> 100k stage: -4.04 / -2.95 dB, session 13).

Once the budget is chosen, the run starts over (``refit``, the default): a fresh model at the
chosen budget, trained from the start on every train view, held-out ones included, exactly as
``--budget N`` would train it (same init, seed and schedules). The selection's own models are
discarded: they trained with views held back, in stages, and with MCMC refining faster, and on
fox (1/16, 2000 iterations) the selection's 50k model, trained on to the end, finished about
1.2 dB below a fixed 50k run. The refit costs one more run; ``selection_seconds`` and
``refit_seconds`` report the two parts. ``refit: false`` trains the selection's model on instead.

Once MCMC has stopped growing the model (``compact_at``, by default the fit's ``refine_stop``),
the model is compacted (``compact``, the default): the primitives are ranked by their blending
weight summed over every train view, and only the most contributing ones are kept, as few as
keep the train-view PSNR within ``compact_tolerance_db`` of the full model's (a bisection over
kept fractions down to ``compact_min_keep``); the rest of the run fine-tunes what is left. The
train views guard the cut because that is what a rule may look at; on the finished auto runs
of session 12 (fox, cup, bonsai, lego at 1/16, 40 cuts) the train-view drop was never smaller
than the test-view drop by more than 0.012 dB, so the guard errs on the safe side. The doubling
stages judge a budget mid-run on a few held-out views, which is noisy (cup's 25k -> 50k stage
gained +0.44 and -1.96 dB on seeds 0 and 1, session 12); the compaction decides the final
size on every train view and every primitive's own contribution.

At the end, primitives that contribute nothing are pruned: opacity below ``prune_opacity``,
or a blending weight ``T * alpha`` summed over every pixel of every train view below
``prune_weight`` (which bounds the largest single weight, so such a primitive never moves any
pixel of any train view by more than ``prune_weight``; never-visible ones sum to 0).

Everything is reported in RUN/fit.json under ``auto_budget``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from ..backends import Backend
from ..colors.base import ColorModel
from ..data.types import Camera
from ..metrics import psnr
from ..train.trainer import StepInfo, Trainer


@dataclass
class AutoBudgetConfig:
    """Settings of ``--budget auto`` (the fit's ``train.budget`` is the reference size)."""

    #: first budget = start_fraction x the fit's budget (100,000 -> 50,000). Half, not a quarter:
    #: the compaction cuts a model back to what it needs, while a first stage judged too small
    #: stays too small (cup and bonsai at 1/16, seeds 0 and 1, stopped at 25,000 on mid-run gains
    #: of -1.96 to +0.45 dB, and ended 0.35 to 1.17 dB below a run with 4x the budget)
    start_fraction: float = 0.5
    #: largest budget tried = max_factor x the fit's budget
    max_factor: float = 4.0
    #: keep doubling while a doubling gains more than this on the held-out views (dB). 0.5, not
    #: the 0.2 of the issue's PSNR tolerance: the stage judges a doubling mid-run, and gains
    #: below 0.5 dB there did not last to the end (fox, 1/16, 2000 iterations, seeds 0 and 1:
    #: 50k -> 100k measured +0.41 / +0.30 dB, yet fixed 50k runs end at 29.77 / 30.19 dB and
    #: the auto runs' 100k at 29.80 / 29.88), while each doubling does double the memory
    threshold_db: float = 0.5
    #: each stage trains for this share of the run (of the iterations, or of the time budget)
    #: (long stages: new primitives cost held-out PSNR for hundreds of iterations before they
    #: pay off, so a short stage judges a doubling too early; on cup at 1/8 resolution, 2000
    #: iterations, stages of 0.125 stopped at 25k (30.64 dB) where fixed runs peak at 50k)
    stage_share: float = 0.25
    #: every n-th train view is held back from the optimiser while choosing (>= 2)
    holdout_every: int = 8
    #: how budgets are compared: "short_runs" (a complete run of stage_share x the iterations per
    #: budget, from the start, judged at its end; needs ``refit``) or "stages" (one run grown
    #: stage by stage, judged mid-run, see ``paired``); see the module doc
    selection: str = "short_runs"
    #: stages: judge a doubling against a control trained through the same stage at the old cap
    paired: bool = True
    #: once the budget is chosen, train a fresh model at it from the start on every train view
    #: (as `--budget N` would); False: train the selection's model on for the rest of the run
    refit: bool = True
    #: without refit: give the held-out views back to the optimiser once the budget is chosen
    return_holdout: bool = True
    #: once growth has ended, keep only the most contributing primitives that hold the train-view
    #: PSNR (see the module doc); the run's remaining iterations fine-tune them
    compact: bool = True
    #: largest train-view PSNR drop the compaction may cost, before fine-tuning (dB). 0.6, not the
    #: issue's 0.2 for "as good as 4x the budget": the train views overstate what a primitive is
    #: worth on new views, and the fine-tuning wins part of the drop back. Session 14 (short runs,
    #: lego, fox, cup, bonsai at 1/16, seeds 0 and 1): from 0.2 to 0.6 the final models shrank
    #: by 14-29% and the test PSNR of each moved by 0.08 dB at most (bonsai seed 0: 27.76 -> 27.68)
    compact_tolerance_db: float = 0.6
    #: never keep fewer than this share of the primitives
    compact_min_keep: float = 0.25
    #: kept fractions the bisection may land on: this many steps from compact_min_keep to 1
    #: (40: steps of 1.9% of the model; at 20, lego seed 1 kept 0.625 of 84,640 where 0.606
    #: held the tolerance too, and ended 56 primitives above half the default, session 14)
    compact_grid_steps: int = 40
    #: run progress at which to compact; None: the fit's refine_stop (MCMC has stopped growing)
    compact_at: float | None = None
    #: at the end, prune primitives with opacity below this
    prune_opacity: float = 1.0 / 255.0
    #: ... or whose blending weight summed over all train-view pixels is below this
    prune_weight: float = 1.0 / 255.0


def split_holdout(train: list[Camera], every: int) -> tuple[list[Camera], list[Camera]]:
    """(optimiser views, held-out views): every ``every``-th train view is held out, at least one,
    and at least one view stays with the optimiser."""
    if len(train) < 2:
        raise ValueError("--budget auto needs at least 2 train views (one is held out)")
    every = max(2, int(every))
    held = {i for i in range(len(train)) if i % every == every // 2} or {len(train) // 2}
    return [c for i, c in enumerate(train) if i not in held], [c for i, c in enumerate(train) if i in held]


@torch.no_grad()
def render_psnr(model, cams: list[Camera], background, backend: Backend) -> float | None:
    """Mean PSNR (dB) of ``model`` rendered with ``backend`` over ``cams`` (renders clamped to
    [0, 1]); None without views."""
    if not cams:
        return None
    bg = torch.as_tensor(background, dtype=torch.float32)
    vals = []
    for cam in cams:
        img = model.render(cam, bg, backend=backend).image
        vals.append(float(psnr(img.cpu(), cam.image_float())))
    return sum(vals) / len(vals)


class _WeightProbe(ColorModel):
    """Stands in for the colour model: every visible primitive's colour is a leaf of ones, so
    d(sum of the image)/d(colour) is the primitive's blending weight summed over the pixels."""

    name = "weight-probe"

    def __init__(self):
        self.leaf: torch.Tensor | None = None

    def colors(self, prims, dirs, degree, backend):
        self.leaf = torch.ones(dirs.shape[0], 3, device=dirs.device, requires_grad=True)
        return self.leaf


def blending_weights(model, cams: list[Camera], backend: Backend) -> torch.Tensor:
    """[N] sum over views and pixels of each primitive's blending weight T * alpha.

    Computed through the renderer itself (the colour model swapped for a probe), so it matches
    what ``model.render`` composites, whatever the backend and kernel.
    """
    total = torch.zeros(model.num_primitives)
    probe, color = _WeightProbe(), model.color
    model.color = probe
    try:
        for cam in cams:
            bg = torch.zeros(3)
            out = model.render(cam, bg, backend=backend)
            if out.visible.numel() == 0:
                continue
            (g,) = torch.autograd.grad(out.image.sum(), probe.leaf)
            total[out.visible.cpu()] += g.detach().cpu().sum(1) / 3.0
    finally:
        model.color = color
    return total


@torch.no_grad()
def render_psnr_keeping(model, rows: torch.Tensor, cams: list[Camera], background,
                        backend: Backend) -> float | None:
    """:func:`render_psnr` of ``model`` with only the primitives ``rows`` (indices); the model
    is left as it was."""
    full = {k: v.data for k, v in model.prims.items()}
    rows = rows.to(next(iter(full.values())).device)
    try:
        for name, p in model.prims.items():
            p.data = full[name][rows]
        return render_psnr(model, cams, background, backend)
    finally:
        for name, p in model.prims.items():
            p.data = full[name]


def compaction_cut(model, cams: list[Camera], background, tolerance_db: float, min_keep: float,
                   backend: Backend, steps: int = 20) -> tuple[torch.Tensor, dict]:
    """Which primitives to keep: the fewest of the most contributing (blending weight summed over
    ``cams``) whose render keeps the mean PSNR over ``cams`` within ``tolerance_db`` of the full
    model's. Kept fractions are tried on a grid of ``steps`` from ``min_keep`` to 1, by bisection
    (the PSNR falls as fewer are kept). Returns ([N] bool keep, report)."""
    weights = blending_weights(model, cams, backend)
    order = torch.argsort(weights, descending=True)
    n = weights.numel()

    def psnr_keeping(k: int) -> float:
        return render_psnr_keeping(model, order[:k], cams, background, backend)

    base = render_psnr(model, cams, background, backend)
    fractions = [min_keep + (1.0 - min_keep) * i / steps for i in range(steps + 1)]
    tried = {}
    lo, hi = 0, steps  # fractions[hi] is within the tolerance (all of them is)
    while lo < hi:
        mid = (lo + hi) // 2
        k = max(1, int(round(n * fractions[mid])))
        tried[k] = psnr_keeping(k)
        if base - tried[k] <= tolerance_db:
            hi = mid
        else:
            lo = mid + 1
    k = max(1, int(round(n * fractions[hi])))
    keep = torch.zeros(n, dtype=torch.bool)
    keep[order[:k]] = True
    after = tried.get(k, base)
    return keep, {"num_primitives_before": n, "num_primitives_after": k, "keep_fraction": k / max(1, n),
                  "train_psnr_before": base, "train_psnr_after": after,
                  "weight_share_kept": float(weights[order[:k]].sum() / weights.sum().clamp_min(1e-12)),
                  "tolerance_db": tolerance_db, "tried": {str(kk): v for kk, v in sorted(tried.items())}}


@torch.no_grad()
def keep_rows(trainer: Trainer, keep: torch.Tensor) -> None:
    """Keep only the primitives ``keep`` ([N] bool), Adam moments included."""
    opt = trainer.opt
    idx = torch.nonzero(keep.to(trainer.device)).flatten()
    for g in opt.opt.param_groups:
        old = g["params"][0]
        new = nn.Parameter(old.data[idx].clone())
        st = opt.opt.state.pop(old, None)
        if st:
            for key in ("exp_avg", "exp_avg_sq"):
                st[key] = st[key][idx].clone()
            opt.opt.state[new] = st
        g["params"][0] = new
        trainer.model.prims[g["name"]] = new


class AutoBudget:
    """Drives a :class:`Trainer` through the budget stages; its state rides in the checkpoint."""

    def __init__(self, cfg: AutoBudgetConfig, base_budget: int, refine_stop: float = 25 / 30):
        self.cfg = cfg
        start = max(1, int(base_budget * cfg.start_fraction))
        budgets = [start]
        while budgets[-1] * 2 <= base_budget * cfg.max_factor:
            budgets.append(budgets[-1] * 2)
        # every stage must end while MCMC still grows the model (progress < refine_stop)
        max_stages = max(1, int(refine_stop / cfg.stage_share + 1e-9))
        self.budgets = budgets[:max_stages]
        self.stages: list[dict] = []
        self.chosen: int | None = None
        self.reason = ""
        self.snapshot: dict | None = None  # trainer state at the end of the last kept stage
        self.holdout_returned = False
        self.prune_report: dict | None = None
        self.compact_report: dict | None = None
        self.refine_every_used: int | None = None
        # paired comparison in progress: which branch is training, the grown branch's result
        self.branch: str | None = None
        self.grown: dict | None = None
        self.comparison_seconds = 0.0
        # refit: True once the fresh model at the chosen budget is training; what the selection
        # cost (its own clock plus the paired controls) and the refit model's initial test PSNR
        self.refitting = False
        self.selection_seconds: float | None = None
        self.selection_iterations: int | None = None
        self.selection_events: list[dict] = []
        # short_runs: the budget whose short run is training (None between runs)
        self.current_short: int | None = None

    @property
    def start_budget(self) -> int:
        return self.budgets[0]

    def state_dict(self) -> dict:
        return {"stages": list(self.stages), "chosen": self.chosen, "reason": self.reason,
                "refine_every_used": self.refine_every_used,
                "snapshot": self.snapshot, "holdout_returned": self.holdout_returned,
                "prune_report": self.prune_report, "compact_report": self.compact_report,
                "branch": self.branch, "grown": self.grown,
                "comparison_seconds": self.comparison_seconds, "refitting": self.refitting,
                "selection_seconds": self.selection_seconds,
                "selection_iterations": self.selection_iterations,
                "selection_events": list(self.selection_events), "current_short": self.current_short}

    def load_state_dict(self, sd: dict) -> None:
        self.stages = list(sd["stages"])
        self.chosen = sd["chosen"]
        self.reason = sd.get("reason", "")
        self.snapshot = sd.get("snapshot")
        self.holdout_returned = sd.get("holdout_returned", False)
        self.prune_report = sd.get("prune_report")
        self.compact_report = sd.get("compact_report")
        self.refine_every_used = sd.get("refine_every_used")
        self.branch = sd.get("branch")
        self.grown = sd.get("grown")
        self.comparison_seconds = sd.get("comparison_seconds", 0.0)
        self.refitting = sd.get("refitting", False)
        self.selection_seconds = sd.get("selection_seconds")
        self.selection_iterations = sd.get("selection_iterations")
        self.selection_events = list(sd.get("selection_events", []))
        self.current_short = sd.get("current_short")

    def return_holdout(self, trainer: Trainer, holdout: list[Camera]) -> None:
        """Hand the held-out views to the optimiser (once the budget is chosen)."""
        trainer.scene.train.extend(holdout)
        trainer.targets.extend(c.image_float(trainer.device) for c in holdout)
        self.holdout_returned = True

    def run(
        self,
        trainer: Trainer,
        holdout: list[Camera],
        on_step: Callable[[StepInfo], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        on_checkpoint: Callable[[Trainer], None] | None = None,
        checkpoint_every: int = 1000,
        make_refit_trainer: Callable[[int], Trainer] | None = None,
        make_short_trainer: Callable[[int], Trainer] | None = None,
    ) -> Trainer:
        """Choose the budget, train at it (with ``refit``: a fresh trainer from
        ``make_refit_trainer(chosen)``, else the selection's own for the rest of the run),
        prune. Returns the trainer that holds the final model, early (state kept for
        ``--resume``) when ``should_stop`` says so."""
        stopped = lambda: bool(should_stop and should_stop())  # noqa: E731
        if self.cfg.selection == "short_runs":
            if not self.cfg.refit or make_short_trainer is None:
                raise ValueError("selection short_runs needs refit and make_short_trainer")
            trainer = self._short_runs(trainer, holdout, make_short_trainer, on_step, should_stop,
                                       on_checkpoint, checkpoint_every)
            if self.chosen is None:  # stopped
                return trainer
        elif self.cfg.selection != "stages":
            raise ValueError(f"unknown selection {self.cfg.selection!r} (stages or short_runs)")
        mcmc = trainer.strategy.cfg
        refine_every = mcmc.refine_every
        if self.chosen is None:
            mcmc.refine_every = self.refine_every_used = self.selection_refine_every(trainer)

        def train_stage(cap: int, end: float) -> bool:
            """Train at MCMC cap ``cap`` until progress ``end``; False if stopped first."""
            trainer.strategy.cfg.cap_max = cap
            trainer.run(on_step, lambda: trainer.progress() >= end - 1e-12 or stopped(),
                        on_checkpoint, checkpoint_every)
            return not stopped()

        while self.chosen is None:
            s = len(self.stages)
            paired = self.cfg.paired and s > 0
            done = (self._paired_stage(trainer, holdout, s, train_stage) if paired
                    else self._unpaired_stage(trainer, holdout, s, train_stage))
            if not done:
                return trainer
        self.snapshot = None
        mcmc.refine_every = refine_every
        if self.cfg.refit and not self.refitting:
            if make_refit_trainer is None:
                raise ValueError("refit needs make_refit_trainer")
            if self.cfg.selection == "stages":
                self.selection_seconds = trainer.elapsed + self.comparison_seconds
                self.selection_iterations = trainer.it
                self.selection_events = list(trainer.events)
            trainer = make_refit_trainer(self.chosen)
            self.refitting = True
            if on_checkpoint:  # a resume from here on rebuilds the refit trainer
                on_checkpoint(trainer)
        if not self.refitting:
            trainer.strategy.cfg.cap_max = self.chosen
            if self.cfg.return_holdout and not self.holdout_returned:
                self.return_holdout(trainer, holdout)
        if self.cfg.compact and self.compact_report is None:
            at = trainer.cfg.refine_stop if self.cfg.compact_at is None else self.cfg.compact_at
            trainer.run(on_step, lambda: trainer.progress() >= at - 1e-12 or stopped(),
                        on_checkpoint, checkpoint_every)
            if stopped() and not trainer.done():
                return trainer
            self.compact_report = self.compact(trainer, holdout)
            if on_checkpoint:  # a resume from here on continues with the compacted model
                on_checkpoint(trainer)
        elif self.compact_report is not None:  # resumed after the compaction: no growing back
            trainer.strategy.cfg.cap_max = trainer.model.num_primitives
        trainer.run(on_step, should_stop, on_checkpoint, checkpoint_every)
        if stopped() and not trainer.done():
            return trainer
        if self.prune_report is None:
            self.prune_report = self.prune(trainer, holdout)
        return trainer

    def _short_runs(self, trainer: Trainer, holdout, make_short_trainer, on_step, should_stop,
                    on_checkpoint, checkpoint_every) -> Trainer:
        """One complete short run per budget, from the start; keep doubling while the held-out
        PSNR at the end of the run gains more than the threshold over the previous budget's."""
        stopped = lambda: bool(should_stop and should_stop())  # noqa: E731
        bg, backend = trainer.background.cpu(), trainer.backend
        while self.chosen is None:
            s = len(self.stages)
            budget = self.budgets[s]
            if self.current_short != budget:
                self.current_short = budget
                trainer = make_short_trainer(budget)
                self.refine_every_used = trainer.strategy.cfg.refine_every
                if on_checkpoint:  # a resume from here on rebuilds this run's trainer
                    on_checkpoint(trainer)
            trainer.run(on_step, should_stop, on_checkpoint, checkpoint_every)
            if stopped() and not trainer.done():
                return trainer
            value = render_psnr(trainer.model, holdout, bg, backend)
            prev = self.stages[-1] if self.stages else None
            gain = None if prev is None else value - prev["holdout_psnr"]
            num = trainer.model.num_primitives
            self.stages.append({"budget": budget, "num_primitives": num, "iteration": trainer.it,
                                "holdout_psnr": value, "gain_db": gain,
                                "seconds": round(trainer.elapsed, 3)})
            self.selection_seconds = (self.selection_seconds or 0.0) + trainer.elapsed
            self.selection_iterations = (self.selection_iterations or 0) + trainer.it
            self.selection_events += trainer.events
            self.current_short = None
            if not self._stop_growing(prev, num, gain, s) and s == len(self.budgets) - 1:
                self.chosen = budget
                self.reason = "largest budget tried (max_factor / stage count)"
        return trainer

    def _unpaired_stage(self, trainer: Trainer, holdout, s: int, train_stage) -> bool:
        """One stage judged against the previous stage's result (``paired: false``)."""
        budget = self.budgets[s]
        if not train_stage(budget, (s + 1) * self.cfg.stage_share):
            return False
        value = render_psnr(trainer.model, holdout, trainer.background.cpu(), trainer.backend)
        num = trainer.model.num_primitives
        prev = self.stages[-1] if self.stages else None
        gain = None if prev is None else value - prev["holdout_psnr"]
        self.stages.append({"budget": budget, "num_primitives": num,
                            "iteration": trainer.it, "holdout_psnr": value, "gain_db": gain})
        if self._stop_growing(prev, num, gain, s):
            self._restore(trainer)  # back to the model before the doubling
        else:
            self._grown_on(trainer, s)
        return True

    def _paired_stage(self, trainer: Trainer, holdout, s: int, train_stage) -> bool:
        """One stage trained twice from the same start: doubled cap vs the current cap."""
        budget, end = self.budgets[s], (s + 1) * self.cfg.stage_share
        bg, backend = trainer.background.cpu(), trainer.backend
        if self.branch != "control":
            self.branch = "grown"
            if not train_stage(budget, end):
                return False
            value = render_psnr(trainer.model, holdout, bg, backend)
            self.grown = {"holdout_psnr": value, "num_primitives": trainer.model.num_primitives,
                          "seconds": trainer.elapsed - self.snapshot["elapsed"],
                          "state": trainer.state_dict()}
            self.branch = "control"
            self._restore(trainer, keep_clock=False)  # the control starts where the grown did
        if not train_stage(self.budgets[s - 1], end):
            return False
        control = render_psnr(trainer.model, holdout, bg, backend)
        grown, self.grown, self.branch = self.grown, None, None
        t_control = trainer.elapsed - self.snapshot["elapsed"]
        gain = grown["holdout_psnr"] - control
        prev = self.stages[-1]
        self.stages.append({"budget": budget, "num_primitives": grown["num_primitives"],
                            "iteration": trainer.it, "holdout_psnr": grown["holdout_psnr"],
                            "control_psnr": control, "gain_db": gain})
        if self._stop_growing(prev, grown["num_primitives"], gain, s):
            self.comparison_seconds += grown["seconds"]  # the control trains on
        else:
            self.comparison_seconds += t_control
            events = list(trainer.events)
            trainer.load_state_dict(grown["state"])  # its clock: the stage trained once
            trainer.events = events
            trainer._snapshot = None  # a NaN rollback must not return to the control model
            self._grown_on(trainer, s)
        return True

    def _stop_growing(self, prev: dict | None, num: int, gain: float | None, s: int) -> bool:
        """Decide after stage ``s``; True when the previous budget is chosen."""
        budget = self.budgets[s]
        # a doubling that MCMC could not carry out (stage shorter than the growth needs, or
        # past the refine window) says nothing about the budget: stop there
        if prev is not None and num < min(0.9 * budget, 1.5 * prev["num_primitives"]):
            self.chosen = self.budgets[s - 1]
            self.reason = (f"the model did not grow in the {budget} stage ({prev['num_primitives']} -> "
                           f"{num} primitives: stage too short for refine_every, or past "
                           f"refine_stop); back to the {self.chosen} model")
            return True
        if gain is not None and not (gain > self.cfg.threshold_db):  # NaN counts as no gain
            self.chosen = self.budgets[s - 1]
            vs = ("the previous budget's short run" if self.cfg.selection == "short_runs" else
                  "its control" if self.cfg.paired else "the previous stage")
            self.reason = (f"doubling {self.budgets[s - 1]} -> {budget} gained {gain:.3f} dB over {vs} "
                           f"<= {self.cfg.threshold_db} dB; back to the {self.chosen} budget")
            return True
        return False

    def _grown_on(self, trainer: Trainer, s: int) -> None:
        """The doubling of stage ``s`` is kept: stop if nothing is left to try, else go on."""
        if trainer.done():
            self.chosen = self.budgets[s]
            self.reason = "the run ended before the gain fell below the threshold"
        elif s == len(self.budgets) - 1:
            self.chosen = self.budgets[s]
            self.reason = "largest budget tried (max_factor / stage count)"
        else:
            self.snapshot = trainer.state_dict()

    def selection_refine_every(self, trainer: Trainer) -> int:
        """MCMC grows 5% per refine step, so a doubling takes 15 of them; while choosing, refine
        often enough that a doubling fits in the first half of a stage (runs with a known
        iteration count; e.g. 3000 iterations, stages of 0.25: every 25 instead of 100 iterations)."""
        every = trainer.strategy.cfg.refine_every
        if trainer.cfg.time_budget:
            return every
        steps = math.ceil(math.log(2.0) / math.log(trainer.strategy.cfg.growth))
        stage_iters = self.cfg.stage_share * trainer.cfg.iters
        return max(1, min(every, int(stage_iters / 2 / steps)))

    def _restore(self, trainer: Trainer, keep_clock: bool = True) -> None:
        """Back to the end of the previous stage; the event log keeps running, and so does the
        clock unless ``keep_clock`` is False (a paired control replays the stage's schedule)."""
        elapsed, events = trainer.elapsed, list(trainer.events)
        trainer.load_state_dict(self.snapshot)
        trainer.events = events
        if keep_clock:
            trainer.elapsed = elapsed
        trainer._snapshot = self.snapshot  # a NaN rollback must not return to the discarded model

    def _every_train_view(self, trainer: Trainer, holdout: list[Camera]) -> list[Camera]:
        """The train views, held-out ones included (the refit trains on all of them already)."""
        return trainer.scene.train if self.holdout_returned or self.refitting else trainer.scene.train + holdout

    def compact(self, trainer: Trainer, holdout: list[Camera]) -> dict:
        """Keep the fewest most-contributing primitives within the train-view PSNR tolerance
        (:func:`compaction_cut`); MCMC's cap follows, so it never grows them back."""
        cams = self._every_train_view(trainer, holdout)
        keep, report = compaction_cut(trainer.model, cams, trainer.background.cpu(), self.cfg.compact_tolerance_db,
                                      self.cfg.compact_min_keep, trainer.backend,
                                      steps=self.cfg.compact_grid_steps)
        if not bool(keep.all()):
            keep_rows(trainer, keep)
        trainer.strategy.cfg.cap_max = trainer.model.num_primitives
        trainer._snapshot = trainer.state_dict()  # a NaN rollback must not return to the full model
        report["iteration"] = trainer.it
        msg = (f"iteration {trainer.it}: compacted {report['num_primitives_before']} -> "
               f"{report['num_primitives_after']} primitives (train-view PSNR "
               f"{report['train_psnr_before']:.2f} -> {report['train_psnr_after']:.2f} dB, tolerance "
               f"{self.cfg.compact_tolerance_db} dB)")
        trainer.events.append({"iteration": trainer.it, "event": "compacted", "message": msg})
        return report

    def prune(self, trainer: Trainer, holdout: list[Camera]) -> dict:
        model, backend = trainer.model, trainer.backend
        bg = trainer.background.cpu()
        cams = self._every_train_view(trainer, holdout)
        before = render_psnr(model, holdout, bg, backend)
        weights = blending_weights(model, cams, backend)
        with torch.no_grad():
            low_opacity = model.opacities.detach().cpu() < self.cfg.prune_opacity
        invisible = weights < self.cfg.prune_weight
        keep = ~(low_opacity | invisible)
        if int(keep.sum()) == 0:  # never prune a model to nothing
            keep[torch.argmax(weights)] = True
        n0 = model.num_primitives
        if not bool(keep.all()):
            keep_rows(trainer, keep)
        after = render_psnr(model, holdout, bg, backend)
        return {"num_primitives_before": n0, "num_primitives_after": model.num_primitives,
                "pruned": n0 - model.num_primitives, "low_opacity": int(low_opacity.sum()),
                "below_weight": int(invisible.sum()), "holdout_psnr_before": before,
                "holdout_psnr_after": after}

    def report(self, holdout: list[Camera]) -> dict:
        return {
            "chosen_budget": self.chosen,
            "start_budget": self.start_budget,
            "budgets_planned": self.budgets,
            "threshold_db": self.cfg.threshold_db,
            "stage_share": self.cfg.stage_share,
            "refine_every_while_choosing": self.refine_every_used,
            "holdout_views": [c.name for c in holdout],
            "holdout_returned_to_training": self.holdout_returned or self.refitting,
            "stages": self.stages,
            "stopped_because": self.reason,
            "selection": self.cfg.selection,
            "paired": self.cfg.paired,
            "comparison_seconds": round(self.comparison_seconds, 3),
            "refit": self.refitting,
            "selection_seconds": (None if self.selection_seconds is None else round(self.selection_seconds, 3)),
            "selection_iterations": self.selection_iterations,
            "selection_events": self.selection_events,
            "compact": self.compact_report,
            "prune": self.prune_report,
            "settings": {k: (v if not isinstance(v, float) or math.isfinite(v) else None)
                         for k, v in vars(self.cfg).items()},
        }
