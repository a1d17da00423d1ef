"""The training loop: render a random train view, DBS loss, Adam, MCMC density control.

Knows nothing of the CLI: progress goes to an ``on_step`` callback, stopping is asked of a
``should_stop`` callback (Ctrl-C handling, time budgets), and the whole state - parameters,
optimiser moments, RNGs, density-control statistics, elapsed time - round-trips through
:meth:`Trainer.state_dict` / :meth:`Trainer.load_state_dict`, which checkpoints, resume and
rollback all use. A rollback (restore the last healthy snapshot, halve every step size) follows
a non-finite loss or parameter, and a collapse without a NaN: the loss's running mean rising
past ``divergence_factor`` x its lowest value or past START_LOSS_FACTOR x its first value, or
every primitive turning invisible (transparent, or shrunk to a vanishing size).
"""
from __future__ import annotations

import copy
import math
import random
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn

from .. import backends
from ..backends import Backend
from ..data.types import Scene
from ..errors import TrainingStalled
from ..models.volumetric import SplatModel
from .losses import photometric_loss, regularisers
from .mcmc import MCMCConfig, MCMCStrategy
from .optim import PrimitiveAdam


#: the loss's running mean (divergence check) averages about this many steps (views)
LOSS_WINDOW = 50
#: periodic rollback snapshots are only taken while the running mean is within this factor of
#: its lowest value
HEALTHY_LOSS_FACTOR = 1.25
#: ... and a run whose running mean rises this far above its first value (the plain mean of its
#: first LOSS_WINDOW steps) is rolled back as well: a run that collapses before it ever improved
#: has its lowest mean near its start, where divergence_factor x lowest cannot see it (short-run
#: LRs and LR x10, 1000 iterations: lego learned k=2 9.65 -> 24.46 dB, fox Gaussian 11.58 -> 16.81
#: dB with this check; benchmarks/results/stability9)
START_LOSS_FACTOR = 1.25
#: a primitive whose largest scale is below this share of the scene's extent draws nothing a
#: camera of the scene resolves (lego at 1/4 resolution: a pixel is ~3e-3 of the extent), and a
#: model of only such primitives (and transparent ones) is rolled back. With short-run LRs and LR
#: x10, lego's learned k=4 shrank every scale to ~1e-6 of the extent while opaque and ended at
#: 11.1 dB, drawn only by the projection's low-pass; caught at 1e-4 it rolled back twice (at
#: iterations 92 and 81, to the init) and ended at 27.0 dB. At 1e-5 the snapshots it went back
#: to were already shrinking, and six rollbacks ended at 11.9 dB.
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


@dataclass
class TrainConfig:
    """Training settings (defaults: 3DGS-MCMC learning rates, DBS loss and density control)."""

    iters: int = 30_000
    #: wall-clock budget in seconds (None: none); schedules follow max(iteration, time) progress
    time_budget: float | None = None
    budget: int = 100_000
    #: sfm | random | auto (sfm when the scene has SfM points, else random)
    init: str = "auto"
    #: random init: number of points (None: a quarter of the budget). MCMC then grows the model
    #: to the budget, and the growth is what carries primitives out of the init box to the
    #: background: on fox (1/8 resolution, 2000 iterations, 50k budget) starting at the budget
    #: gave 24.40 dB, at a quarter 26.65 dB. 3DGS-MCMC starts at a tenth or less of its cap.
    random_points: int | None = None
    #: initial scale = init_scale x neighbour spacing (0: 0.1 for random init, 1 for SfM as DBS)
    init_scale: float = 0.0
    seed: int = 0
    lambda_dssim: float = 0.2
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh_degree_interval: int = 1000
    refine_every: int = 100
    refine_start: int = 500
    refine_stop: float = 25 / 30
    noise_lr: float = 5e4
    #: MCMC split copies' scales: keep (DBS) | shrink (3DGS-MCMC Eq. 9; see splatk.train.mcmc)
    split_scales: str = "keep"
    #: MCMC skips a step's growth while that step relocated at least as many dead primitives
    #: as it would add (splatk.train.mcmc MCMCStrategy.step)
    hold_growth: bool = True
    #: multiplies every learning rate (primitives, colour, kernel networks); 1 = the defaults
    lr_scale: float = 1.0
    #: multiplies the log-scale learning rate alone. 0.005 is tuned for 30k iterations; short
    #: runs starve it (benchmarks/README.md, "short runs"), so bench runs raise it
    scales_lr_mult: float = 1.0
    backend: str = "auto"
    device: str = "cpu"
    #: keep an in-memory snapshot this often for rollback (NaN or collapse)
    snapshot_every: int = 200
    #: roll back (as for a NaN) when the loss's running mean rises above this many times its
    #: lowest value: a run can collapse to an empty image without a NaN (cup, learning rates
    #: x10, 1000 iterations: loss 0.10 -> 0.66, 4.8 dB). Early collapses, whose lowest mean is
    #: still near the initial loss, are left to the START_LOSS_FACTOR test: 1.5 here caught them
    #: too, but also fired on healthy growth (bonsai, --budget auto, the 50k -> 100k stage: mean
    #: 0.065 vs lowest 0.043 while MCMC doubled the model, on both seeds). 0 turns every
    #: collapse check off.
    divergence_factor: float = 2.0


@dataclass
class StepInfo:
    it: int
    iters: int
    loss: float
    psnr: float
    num_primitives: int
    elapsed: float
    progress: float
    event: str | None = None


class Trainer:
    """Trains ``model`` on ``scene``. ``backend``: the ops every step uses; default
    ``backends.get(config.backend, config.device)``, resolved here once (a benchmark may pass
    its own object)."""

    def __init__(self, scene: Scene, model: SplatModel, config: TrainConfig, backend: Backend | None = None):
        self.scene = scene
        self.cfg = config
        self.device = torch.device(config.device)
        self.backend = backends.get(config.backend, self.device) if backend is None else backend
        self.model = model.to(self.device)
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=self.device)
        self.extent = scene.extent
        self.it = 0
        self.elapsed = 0.0
        self.events: list[dict] = []
        self.lr_scale = 1.0  # lowered after a NaN rollback
        # running mean of the loss (about the last LOSS_WINDOW steps), its lowest value and its
        # first value (once it has seen LOSS_WINDOW steps)
        self.loss_mean: float | None = None
        self.best_loss_mean: float | None = None
        self.start_loss_mean: float | None = None
        self._steps_since_reset = 0
        self.view_gen = torch.Generator().manual_seed(config.seed)
        self.mcmc_gen = torch.Generator(device=self.device).manual_seed(config.seed + 1)
        self._view_queue: list[int] = []
        self.strategy = MCMCStrategy(
            MCMCConfig(
                cap_max=config.budget, refine_every=config.refine_every,
                refine_start=config.refine_start, refine_stop=config.refine_stop,
                noise_lr=config.noise_lr, split_scales=config.split_scales,
                hold_growth=config.hold_growth,
            )
        )
        self._build_optimizers()
        self.targets = [c.image_float(self.device) for c in scene.train]
        self._snapshot = None
        # False while the snapshot a rollback would restore is itself all invisible
        self._invisible_check = True
        # False once MAX_REPEATED_LOSS_ROLLBACKS to one snapshot did not stop a loss rise (until
        # the next snapshot); the series: [snapshot iteration, rollbacks, step size before them]
        self._loss_check = True
        self._loss_rollback_series: list | None = None
        # [snapshot iteration, rollbacks to it]: MAX_ROLLBACKS_WITHOUT_PROGRESS stops the fit
        self._rollbacks_to_snapshot: list | None = None

    # ---- optimisers and schedules ------------------------------------------------------
    def _build_optimizers(self) -> None:
        lrs = self.model.learning_rates()
        lrs["means"] = self.cfg.means_lr * self.extent
        lrs["log_scales"] *= self.cfg.scales_lr_mult
        self.opt = PrimitiveAdam(self.model.prims, lrs)
        net_params = list(self.model.kernel.parameters())
        self.net_opt = torch.optim.Adam(net_params, lr=0.0) if net_params else None

    def progress(self) -> float:
        p = self.it / max(1, self.cfg.iters)
        if self.cfg.time_budget:
            p = max(p, self.elapsed / self.cfg.time_budget)
        return min(1.0, p)

    def means_lr(self, progress: float) -> float:
        """Log-linear decay 1.6e-4 -> 1.6e-6, times the scene extent (3DGS)."""
        lo, hi = self.cfg.means_lr_final, self.cfg.means_lr
        return math.exp((1 - progress) * math.log(hi) + progress * math.log(lo)) * self.extent

    def sh_degree(self) -> int:
        return self.it // self.cfg.sh_degree_interval

    def _next_view(self) -> int:
        if not self._view_queue:
            self._view_queue = torch.randperm(len(self.targets), generator=self.view_gen).tolist()
        return self._view_queue.pop()

    # ---- one iteration -----------------------------------------------------------------
    def train_step(self) -> StepInfo:
        t0 = time.perf_counter()
        self.it += 1
        p = self.progress()
        lr_scale = self.lr_scale * self.cfg.lr_scale  # rollback halving x the configured multiplier
        means_lr = self.means_lr(p) * lr_scale
        self.opt.set_lr("means", means_lr)
        if lr_scale != 1.0:
            for name, lr in self.opt.base_lrs.items():
                if name != "means":
                    self.opt.set_lr(name, lr * lr_scale)
        if self.net_opt is not None:
            for g in self.net_opt.param_groups:
                g["lr"] = self.model.kernel.network_learning_rate(self.it, p) * lr_scale
        vi = self._next_view()
        cam = self.scene.train[vi]
        target = self.targets[vi]
        out = self.model.render(cam, self.background, sh_degree=self.sh_degree(), backend=self.backend)
        loss = photometric_loss(out.image, target, self.backend, self.cfg.lambda_dssim)
        loss = loss + regularisers(self.model, self.cfg.opacity_reg, self.cfg.scale_reg)
        event = None
        if not torch.isfinite(loss):
            event = self._rollback("non-finite loss")
        else:
            self.opt.zero_grad()
            if self.net_opt is not None:
                self.net_opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
            if self.net_opt is not None and any(g["lr"] > 0 for g in self.net_opt.param_groups):
                self.net_opt.step()
            with torch.no_grad():
                self.model.prims["quats"].data = torch.nn.functional.normalize(self.model.prims["quats"].data, dim=-1)
            if not self._params_finite():
                event = self._rollback("non-finite parameters")
            elif self._diverging(float(loss.detach())) and self._loss_check:
                reason = f"loss diverged (running mean {self.loss_mean:.4g}, lowest {self.best_loss_mean:.4g})"
                event = (self._loss_check_off(reason) if self._repeated_loss_rollbacks()
                         else self._rollback(reason, kind="loss_rollback", loss_rise=True))
            elif self._all_invisible():
                event = self._rollback("every primitive is transparent (opacity <= "
                                       f"{self.strategy.cfg.min_opacity:g}) or vanishingly small "
                                       f"(scales < {VANISHED_SCALE:g} x the scene extent)", kind="loss_rollback")
            else:
                self.strategy.step(self.it, p, self.model, self.opt, means_lr, self.mcmc_gen)
                event = self._note_growth_held()
                # a snapshot taken while the loss is already climbing would be rolled back to
                if (self.it % self.cfg.snapshot_every == 0 and self._loss_healthy()
                        and not self._model_invisible()):
                    self._snapshot = self.state_dict()
                    self._invisible_check = True
                    self._loss_check, self._loss_rollback_series = True, None
        with torch.no_grad():
            mse = ((out.image.detach().clamp(0, 1) - target) ** 2).mean().item()
        self.elapsed += time.perf_counter() - t0
        return StepInfo(
            self.it, self.cfg.iters, float(loss.detach()), -10 * math.log10(max(mse, 1e-10)),
            self.model.num_primitives, self.elapsed, self.progress(), event,
        )

    def _params_finite(self) -> bool:
        # A sum is non-finite iff some element is (inf - inf gives NaN too), and one sum per
        # tensor is far cheaper than a full isfinite mask (finite float32 parameters stay far
        # below the overflow range).
        sums = [p.detach().sum() for p in self.model.prims.values()]
        sums += [p.detach().sum() for p in self.model.kernel.parameters()]
        return bool(torch.isfinite(torch.stack(sums)).all()) if sums else True

    def _diverging(self, loss: float) -> bool:
        """Update the loss's running mean; True when it has risen past ``divergence_factor`` x
        its lowest value or past START_LOSS_FACTOR x its first value (judged once the mean has
        seen LOSS_WINDOW steps since the last reset)."""
        self._steps_since_reset += 1
        # the plain mean over the first LOSS_WINDOW steps, then an exponential one: seeding the
        # exponential mean with the first loss would let one easy (or hard) view set the level
        # that the rest of the run is judged against
        a = 1.0 / min(self._steps_since_reset, LOSS_WINDOW)
        self.loss_mean = loss if self.loss_mean is None else (1 - a) * self.loss_mean + a * loss
        if self._steps_since_reset < LOSS_WINDOW:
            return False
        if self.start_loss_mean is None:
            self.start_loss_mean = self.loss_mean
        if self.best_loss_mean is None or self.loss_mean < self.best_loss_mean:
            self.best_loss_mean = self.loss_mean
        f = self.cfg.divergence_factor
        return f > 0 and (self.loss_mean > f * self.best_loss_mean
                          or self.loss_mean > START_LOSS_FACTOR * self.start_loss_mean)

    def _all_invisible(self) -> bool:
        """True when no primitive is both above MCMC's dead-opacity line and larger than
        VANISHED_SCALE x the extent. Relocation and growth sample live primitives, so a fully
        transparent model can never come back, and its loss need not rise enough to trip
        :meth:`_diverging` (lego, Beta, short-run LRs and LR x10: the scales and opacities shrank
        to nothing by iteration 60, and the empty white image's loss, 0.215, stayed below the
        random init's 0.33 and within 1.2x of the run's first mean). Vanished scales get no
        useful gradient either: the low-pass draws every such primitive as the same dot."""
        if self.cfg.divergence_factor <= 0 or not self._invisible_check:
            return False
        return self._model_invisible()

    def _model_invisible(self) -> bool:
        logits = self.model.prims["opacity_logits"].detach()
        if logits.numel() == 0:
            return False
        dead = math.log(self.strategy.cfg.min_opacity / (1.0 - self.strategy.cfg.min_opacity))
        log_size = self.model.prims["log_scales"].detach().max(dim=-1).values
        visible = (logits > dead) & (log_size > math.log(VANISHED_SCALE * self.extent))
        return not bool(visible.any())

    def _loss_healthy(self) -> bool:
        # near the lowest mean, and no worse than where the run started: a snapshot of a run
        # that is collapsing from the start would otherwise replace the good initial one
        if self.best_loss_mean is None:
            return True
        return (self.loss_mean <= HEALTHY_LOSS_FACTOR * self.best_loss_mean
                and self.loss_mean <= self.start_loss_mean)

    def _repeated_loss_rollbacks(self) -> bool:
        """True when MAX_REPEATED_LOSS_ROLLBACKS rollbacks to the current snapshot have each
        been followed by another loss rise."""
        series = self._loss_rollback_series
        return (series is not None and self._snapshot is not None and series[0] == self._snapshot["it"]
                and series[1] >= MAX_REPEATED_LOSS_ROLLBACKS)

    def _loss_check_off(self, reason: str) -> str:
        """Keep the current state, give the step size back, stop judging the loss until the
        next snapshot: the rise is the model's own (growth), and rolling back again would only
        repeat it at a smaller step."""
        it, (snap_it, count, lr_before) = self.it, self._loss_rollback_series
        self.lr_scale = lr_before
        self._loss_check = False
        self.loss_mean, self.best_loss_mean, self.start_loss_mean, self._steps_since_reset = None, None, None, 0
        msg = (f"iteration {it}: {reason} again after {count} rollbacks to iteration {snap_it}; kept "
               f"going, step size back to x{lr_before:g}, loss check off until the next snapshot")
        self.events.append({"iteration": it, "event": "loss_check_off", "message": msg})
        return msg

    def _rollback(self, reason: str, kind: str = "nan_rollback", loss_rise: bool = False) -> str:
        """Never die of a NaN (or a collapse): restore the last good state, halve the step
        sizes, go on; stop (TrainingStalled) when that keeps failing from the same state."""
        it, lr_scale = self.it, self.lr_scale
        snap_it = self._snapshot["it"] if self._snapshot is not None else None
        count = self._rollbacks_to_snapshot
        self._rollbacks_to_snapshot = [snap_it, count[1] + 1 if count and count[0] == snap_it else 1]
        if self._rollbacks_to_snapshot[1] > MAX_ROLLBACKS_WITHOUT_PROGRESS:
            self.events.append({"iteration": it, "event": "stalled", "message": f"iteration {it}: {reason}"})
            raise TrainingStalled(f"iteration {it}: {reason}, after {MAX_ROLLBACKS_WITHOUT_PROGRESS} rollbacks to "
                                  f"iteration {snap_it} at ever smaller step sizes", STALL_CAUSES[kind])
        if loss_rise and self._snapshot is not None:
            series = self._loss_rollback_series
            if series is not None and series[0] == self._snapshot["it"]:
                series[1] += 1
            else:
                self._loss_rollback_series = [self._snapshot["it"], 1, lr_scale]
        if self._snapshot is not None:
            # the step-size cut below survives the restore: restoring the snapshot's own
            # lr_scale would retry the same diverging steps forever
            self.restore_last_healthy()
        else:  # NaN before the first snapshot: drop the non-finite primitives' updates
            with torch.no_grad():
                for p in self.model.prims.values():
                    p.data = torch.nan_to_num(p.data, nan=0.0, posinf=0.0, neginf=0.0)
        self.lr_scale = lr_scale * 0.5
        # the check starts again from the restored state's losses, lowest value included: the
        # snapshot can already be worse than the lowest mean (the mean lags the loss), and
        # judging it against that would roll back to it again and again at ever smaller steps
        self.loss_mean, self.best_loss_mean, self.start_loss_mean, self._steps_since_reset = None, None, None, 0
        # a snapshot that is itself all invisible cannot be helped by rolling back to it again
        self._invisible_check = not self._model_invisible()
        msg = f"iteration {it}: {reason}; rolled back to iteration {self.it}, step size x{self.lr_scale:g}"
        self.events.append({"iteration": it, "event": kind, "message": msg})
        return msg

    def restore_last_healthy(self) -> None:
        """Go back to the last snapshot taken while training was healthy (keeping the clock and
        the event log), e.g. to checkpoint it when training stalls."""
        if self._snapshot is not None:
            elapsed, events = self.elapsed, list(self.events)
            self.load_state_dict(self._snapshot)
            self.elapsed, self.events = elapsed, events

    # ---- the loop ----------------------------------------------------------------------
    def done(self) -> bool:
        if self.it >= self.cfg.iters:
            return True
        return bool(self.cfg.time_budget) and self.elapsed >= self.cfg.time_budget

    def run(
        self,
        on_step: Callable[[StepInfo], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        on_checkpoint: Callable[["Trainer"], None] | None = None,
        checkpoint_every: int = 1000,
    ) -> None:
        if self.it == 0:  # a resumed run has the global RNG of its checkpoint (load_state_dict)
            torch.manual_seed(self.cfg.seed)
        if self._snapshot is None:  # a NaN before the first periodic snapshot goes back to here
            self._snapshot = self.state_dict()
        while not self.done():
            info = self.train_step()
            if on_step:
                on_step(info)
            if on_checkpoint and self.it % checkpoint_every == 0:
                on_checkpoint(self)
            if should_stop and should_stop():
                break

    def _note_growth_held(self) -> str | None:
        """Log the first refine step whose growth MCMC held back (mcmc.MCMCStrategy.step), so a
        model that ends below its budget says why; later ones are not logged."""
        stats = self.strategy.last_stats
        if not stats.get("growth_held") or any(e["event"] == "growth_held" for e in self.events):
            return None
        msg = (f"iteration {self.it}: MCMC held growth at {stats['num']} primitives: the step found "
               f"{stats['relocated']} dead, at least as many as it would add; it grows again once "
               "fewer die (first occurrence; the model may end below its budget)")
        self.events.append({"iteration": self.it, "event": "growth_held", "message": msg})
        return msg

    # ---- state ---------------------------------------------------------------------------
    @staticmethod
    def _numpy_rng_state() -> tuple:
        """``np.random.get_state()`` with its key array as an int64 tensor."""
        name, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
        return name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached_gaussian)

    @staticmethod
    def _set_numpy_rng_state(state) -> None:
        name, keys, pos, has_gauss, cached_gaussian = state
        np.random.set_state((name, keys.cpu().numpy().astype(np.uint32), pos, has_gauss, cached_gaussian))

    def state_dict(self) -> dict:
        return {
            "it": self.it,
            "elapsed": self.elapsed,
            "lr_scale": self.lr_scale,
            "events": list(self.events),
            "loss_mean": (self.loss_mean, self.best_loss_mean, self._steps_since_reset, self.start_loss_mean),
            "prims": {k: v.detach().clone() for k, v in self.model.prims.items()},
            "kernel": copy.deepcopy(self.model.kernel.state_dict()),
            "opt": copy.deepcopy(self.opt.state_dict()),
            "net_opt": copy.deepcopy(self.net_opt.state_dict()) if self.net_opt else None,
            "view_gen": self.view_gen.get_state(),
            "mcmc_gen": self.mcmc_gen.get_state(),
            "view_queue": list(self._view_queue),
            "torch_rng": torch.get_rng_state(),
            # plain values and tensors only, so that checkpoints load with weights_only=True
            # (numpy's state holds an array: its 624 uint32 keys go in an int64 tensor)
            "numpy_rng": self._numpy_rng_state(),
            "python_rng": random.getstate(),  # (version, tuple of ints, float or None)
            # draws on a GPU without a generator of ours (torch's default one there)
            "cuda_rng": torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None,
            "config": asdict(self.cfg),
        }

    def load_state_dict(self, sd: dict) -> None:
        self.it = sd["it"]
        self.elapsed = sd["elapsed"]
        self.lr_scale = sd.get("lr_scale", 1.0)
        self.events = list(sd.get("events", []))
        # checkpoints before the start-loss check hold three values; theirs starts afresh
        mean, best, steps, start = (tuple(sd.get("loss_mean", (None, None, 0))) + (None,))[:4]
        self.loss_mean, self.best_loss_mean, self._steps_since_reset = mean, best, steps
        self.start_loss_mean = start
        self.model.prims = nn.ParameterDict(
            {k: nn.Parameter(v.clone().to(self.device)) for k, v in sd["prims"].items()}
        )
        self.model.kernel.load_state_dict(sd["kernel"])
        self._build_optimizers()
        # deep copy: Optimizer.load_state_dict keeps the given tensors, and Adam updates its
        # moments and step counts in place, which would rewrite a rollback snapshot
        self.opt.load_state_dict(copy.deepcopy(sd["opt"]))
        if self.net_opt is not None and sd.get("net_opt") is not None:
            self.net_opt.load_state_dict(copy.deepcopy(sd["net_opt"]))
        # generator states are CPU byte tensors whatever the device (a checkpoint loaded with
        # map_location="cuda" moves them there)
        self.view_gen.set_state(sd["view_gen"].cpu())
        self.mcmc_gen.set_state(sd["mcmc_gen"].cpu())
        self._view_queue = list(sd["view_queue"])
        torch.set_rng_state(sd["torch_rng"].cpu())
        if sd.get("cuda_rng") is not None and self.device.type == "cuda":
            torch.cuda.set_rng_state(sd["cuda_rng"].cpu(), self.device)
        self._set_numpy_rng_state(sd["numpy_rng"])
        version, internal, gauss_next = sd["python_rng"]
        random.setstate((version, tuple(internal), gauss_next))
