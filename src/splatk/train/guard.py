"""The trainer's guard: rollbacks after a non-finite loss or parameter and after a collapse
without a NaN, and the stop when rollbacks do not help.

A collapse is the loss's running mean rising past ``divergence_factor`` x its lowest value or
past START_LOSS_FACTOR x its first value, or every primitive turning invisible (transparent, or
shrunk to a vanishing size). A rollback restores the last healthy snapshot (a
:meth:`Trainer.state_dict <splatk.train.trainer.Trainer.state_dict>`) and halves every step size.
"""
from __future__ import annotations

import math

import torch

from ..errors import TrainingStalled


#: the loss's running mean (divergence check) averages about this many steps (views)
LOSS_WINDOW = 50
#: periodic rollback snapshots are only taken while the running mean is within this factor of
#: its lowest value
HEALTHY_LOSS_FACTOR = 1.25
#: ... and a run whose running mean rises this far above its first value (the plain mean of its
#: first LOSS_WINDOW steps) is rolled back as well: a run that collapses before it ever improved
#: has its lowest mean near its start, where divergence_factor x lowest cannot see it
#: (docs/decisions/0005-collapse-rollback.md)
START_LOSS_FACTOR = 1.25
#: a primitive whose largest scale is below this share of the scene's extent draws nothing a
#: camera of the scene resolves (lego at 1/4 resolution: a pixel is ~3e-3 of the extent), and a
#: model of only such primitives (and transparent ones) is rolled back: with LRs x10 a learned
#: model can shrink every scale to ~1e-6 of the extent while staying opaque, drawn only by the
#: projection's low-pass. 1e-5 caught it too late: the snapshots it went back to were already
#: shrinking (docs/decisions/0005-collapse-rollback.md).
VANISHED_SCALE = 1e-4
#: a loss rise that comes back after this many rollbacks to the same snapshot is not the step
#: size's doing: the loss check goes off (until the next snapshot) and the step size returns to
#: where it was before the first of them. Bonsai at 1/16 with a 400k budget (2000 iterations):
#: MCMC's growth from 200k to 400k around iteration 350 raised the running mean past the check
#: every time, and without this limit the run rolled back to iteration 200 nine times in 36
#: minutes of training, the step size down to x0.002, without getting past iteration 400 (a
#: whole 200k run takes 8 minutes).
MAX_REPEATED_LOSS_ROLLBACKS = 3
#: rollbacks to one snapshot, each at half the step size of the one before, after which the
#: fit stops (TrainingStalled): at 1/256 of the step size a failure that still comes back is not
#: the step size's doing, and going on would loop without end
MAX_ROLLBACKS_WITHOUT_PROGRESS = 8
#: what to tell the user when rollbacks of each kind do not help
STALL_CAUSES = {
    "nan_rollback": "the loss or the parameters turn non-finite whatever the step size: degenerate "
                    "cameras or images, or settings far outside their range (lr_scale, noise_lr)",
    "loss_rollback": "the model collapses or diverges whatever the step size: a budget too small for the "
                     "scene, or learning rates or regularisers far from their defaults",
}


class Guard:
    """The checks of one :class:`~splatk.train.trainer.Trainer` and the snapshot they go back
    to. The trainer asks :meth:`after_nan_loss` or :meth:`after_step` once per iteration and
    :meth:`note_step` when the step stood."""

    def __init__(self, trainer):
        self.trainer = trainer
        # running mean of the loss (about the last LOSS_WINDOW steps), its lowest value and its
        # first value (once it has seen LOSS_WINDOW steps)
        self.loss_mean: float | None = None
        self.best_loss_mean: float | None = None
        self.start_loss_mean: float | None = None
        self.steps_since_reset = 0
        self.snapshot: dict | None = None
        # False while the snapshot a rollback would restore is itself all invisible
        self.invisible_check = True
        # False once MAX_REPEATED_LOSS_ROLLBACKS to one snapshot did not stop a loss rise (until
        # the next snapshot); the series: [snapshot iteration, rollbacks, step size before them]
        self.loss_check = True
        self.loss_rollback_series: list | None = None
        # [snapshot iteration, rollbacks to it]: MAX_ROLLBACKS_WITHOUT_PROGRESS stops the fit
        self.rollbacks_to_snapshot: list | None = None

    # ---- per iteration ---------------------------------------------------------------------
    def after_nan_loss(self) -> str:
        return self.rollback("non-finite loss")

    def after_step(self, loss: float) -> str | None:
        """Judge the step just taken; the event message of a rollback (or of the loss check
        going off), None when the step stands."""
        if not self.params_finite():
            return self.rollback("non-finite parameters")
        if self.diverging(loss) and self.loss_check:
            reason = f"loss diverged (running mean {self.loss_mean:.4g}, lowest {self.best_loss_mean:.4g})"
            return (self.loss_check_off(reason) if self.repeated_loss_rollbacks()
                    else self.rollback(reason, kind="loss_rollback", loss_rise=True))
        if self.all_invisible():
            min_opacity = self.trainer.strategy.cfg.min_opacity
            return self.rollback(f"every primitive is transparent (opacity <= {min_opacity:g}) or vanishingly "
                                 f"small (scales < {VANISHED_SCALE:g} x the scene extent)", kind="loss_rollback")
        return None

    def note_step(self) -> None:
        """After a step that stood: take the periodic snapshot while training is healthy (a
        snapshot taken while the loss is already climbing would be rolled back to)."""
        tr = self.trainer
        if tr.it % tr.cfg.snapshot_every == 0 and self.loss_healthy() and not self.model_invisible():
            self.snapshot = tr.state_dict()
            self.invisible_check = True
            self.loss_check, self.loss_rollback_series = True, None

    # ---- the checks ------------------------------------------------------------------------
    def params_finite(self) -> bool:
        # A sum is non-finite iff some element is (inf - inf gives NaN too), and one sum per
        # tensor is far cheaper than a full isfinite mask (finite float32 parameters stay far
        # below the overflow range).
        model = self.trainer.model
        sums = [p.detach().sum() for p in model.prims.values()]
        sums += [p.detach().sum() for p in model.kernel.parameters()]
        return bool(torch.isfinite(torch.stack(sums)).all()) if sums else True

    def diverging(self, loss: float) -> bool:
        """Update the loss's running mean; True when it has risen past ``divergence_factor`` x
        its lowest value or past START_LOSS_FACTOR x its first value (judged once the mean has
        seen LOSS_WINDOW steps since the last reset)."""
        self.steps_since_reset += 1
        # the plain mean over the first LOSS_WINDOW steps, then an exponential one: seeding the
        # exponential mean with the first loss would let one easy (or hard) view set the level
        # that the rest of the run is judged against
        a = 1.0 / min(self.steps_since_reset, LOSS_WINDOW)
        self.loss_mean = loss if self.loss_mean is None else (1 - a) * self.loss_mean + a * loss
        if self.steps_since_reset < LOSS_WINDOW:
            return False
        if self.start_loss_mean is None:
            self.start_loss_mean = self.loss_mean
        if self.best_loss_mean is None or self.loss_mean < self.best_loss_mean:
            self.best_loss_mean = self.loss_mean
        f = self.trainer.cfg.divergence_factor
        return f > 0 and (self.loss_mean > f * self.best_loss_mean
                          or self.loss_mean > START_LOSS_FACTOR * self.start_loss_mean)

    def all_invisible(self) -> bool:
        """True when no primitive is both above MCMC's dead-opacity line and larger than
        VANISHED_SCALE x the extent. Relocation and growth sample live primitives, so a fully
        transparent model can never come back, and its loss need not rise enough to trip
        :meth:`diverging` (lego, Beta, short-run LRs and LR x10: the scales and opacities shrank
        to nothing by iteration 60, and the empty white image's loss, 0.215, stayed below the
        random init's 0.33 and within 1.2x of the run's first mean). Vanished scales get no
        useful gradient either: the low-pass draws every such primitive as the same dot."""
        if self.trainer.cfg.divergence_factor <= 0 or not self.invisible_check:
            return False
        return self.model_invisible()

    def model_invisible(self) -> bool:
        tr = self.trainer
        logits = tr.model.prims["opacity_logits"].detach()
        if logits.numel() == 0:
            return False
        min_opacity = tr.strategy.cfg.min_opacity
        dead = math.log(min_opacity / (1.0 - min_opacity))
        log_size = tr.model.prims["log_scales"].detach().max(dim=-1).values
        visible = (logits > dead) & (log_size > math.log(VANISHED_SCALE * tr.extent))
        return not bool(visible.any())

    def loss_healthy(self) -> bool:
        # near the lowest mean, and no worse than where the run started: a snapshot of a run
        # that is collapsing from the start would otherwise replace the good initial one
        if self.best_loss_mean is None:
            return True
        return (self.loss_mean <= HEALTHY_LOSS_FACTOR * self.best_loss_mean
                and self.loss_mean <= self.start_loss_mean)

    def repeated_loss_rollbacks(self) -> bool:
        """True when MAX_REPEATED_LOSS_ROLLBACKS rollbacks to the current snapshot have each
        been followed by another loss rise."""
        series = self.loss_rollback_series
        return (series is not None and self.snapshot is not None and series[0] == self.snapshot["it"]
                and series[1] >= MAX_REPEATED_LOSS_ROLLBACKS)

    def reset_loss_stats(self) -> None:
        self.loss_mean, self.best_loss_mean, self.start_loss_mean, self.steps_since_reset = None, None, None, 0

    # ---- what the checks do ----------------------------------------------------------------
    def loss_check_off(self, reason: str) -> str:
        """Keep the current state, give the step size back, stop judging the loss until the
        next snapshot: the rise is the model's own (growth), and rolling back again would only
        repeat it at a smaller step."""
        tr = self.trainer
        it, (snap_it, count, lr_before) = tr.it, self.loss_rollback_series
        tr.lr_scale = lr_before
        self.loss_check = False
        self.reset_loss_stats()
        msg = (f"iteration {it}: {reason} again after {count} rollbacks to iteration {snap_it}; kept "
               f"going, step size back to x{lr_before:g}, loss check off until the next snapshot")
        tr.events.append({"iteration": it, "event": "loss_check_off", "message": msg})
        return msg

    def rollback(self, reason: str, kind: str = "nan_rollback", loss_rise: bool = False) -> str:
        """Never die of a NaN (or a collapse): restore the last good state, halve the step
        sizes, go on; stop (TrainingStalled) when that keeps failing from the same state."""
        tr = self.trainer
        it, lr_scale = tr.it, tr.lr_scale
        snap_it = self.snapshot["it"] if self.snapshot is not None else None
        count = self.rollbacks_to_snapshot
        self.rollbacks_to_snapshot = [snap_it, count[1] + 1 if count and count[0] == snap_it else 1]
        if self.rollbacks_to_snapshot[1] > MAX_ROLLBACKS_WITHOUT_PROGRESS:
            tr.events.append({"iteration": it, "event": "stalled", "message": f"iteration {it}: {reason}"})
            raise TrainingStalled(f"iteration {it}: {reason}, after {MAX_ROLLBACKS_WITHOUT_PROGRESS} rollbacks to "
                                  f"iteration {snap_it} at ever smaller step sizes", STALL_CAUSES[kind])
        if loss_rise and self.snapshot is not None:
            series = self.loss_rollback_series
            if series is not None and series[0] == self.snapshot["it"]:
                series[1] += 1
            else:
                self.loss_rollback_series = [self.snapshot["it"], 1, lr_scale]
        if self.snapshot is not None:
            # the step-size cut below survives the restore: restoring the snapshot's own
            # lr_scale would retry the same diverging steps forever
            self.restore_last_healthy()
        else:  # NaN before the first snapshot: drop the non-finite primitives' updates
            with torch.no_grad():
                for p in tr.model.prims.values():
                    p.data = torch.nan_to_num(p.data, nan=0.0, posinf=0.0, neginf=0.0)
        tr.lr_scale = lr_scale * 0.5
        # the check starts again from the restored state's losses, lowest value included: the
        # snapshot can already be worse than the lowest mean (the mean lags the loss), and
        # judging it against that would roll back to it again and again at ever smaller steps
        self.reset_loss_stats()
        # a snapshot that is itself all invisible cannot be helped by rolling back to it again
        self.invisible_check = not self.model_invisible()
        msg = f"iteration {it}: {reason}; rolled back to iteration {tr.it}, step size x{tr.lr_scale:g}"
        tr.events.append({"iteration": it, "event": kind, "message": msg})
        return msg

    def restore_last_healthy(self) -> None:
        """Go back to the snapshot (keeping the trainer's clock and event log)."""
        tr = self.trainer
        if self.snapshot is not None:
            elapsed, events = tr.elapsed, list(tr.events)
            tr.load_state_dict(self.snapshot)
            tr.elapsed, tr.events = elapsed, events
