"""The training loop: render a random train view, DBS loss, Adam, MCMC density control.

Knows nothing of the CLI: progress goes to an ``on_step`` callback, stopping is asked of a
``should_stop`` callback (Ctrl-C handling, time budgets). Two helpers keep the loop short: the
guard (:mod:`splatk.train.guard`) rolls back to the last healthy snapshot after a NaN or a
collapse and stops a run that rollbacks do not help; the state (:mod:`splatk.train.state`) -
parameters, optimiser moments, RNGs, density-control statistics, elapsed time - round-trips
through :meth:`Trainer.state_dict` / :meth:`Trainer.load_state_dict`, which checkpoints, resume
and rollback all use.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields
from typing import Callable

import torch

from .. import backends
from ..backends import Backend
from ..data.types import Scene
from ..models.volumetric import SplatModel
from .adc import ADCConfig  # importing adc and mcmc registers their strategies
from .distributed import SINGLE, World, my_share, statistics_before
from .guard import Guard
from .losses import masked_mse, photometric_loss, regularisers
from .mcmc import MCMCConfig
from .optim import PrimitiveAdam
from .planar_regularisers import GeometryTerms
from .state import load_trainer_state, trainer_state
from .strategies import make_strategy

#: TrainConfig.mcmc's fields, which config files written before it existed hold at the top level
MCMC_FIELDS = tuple(f.name for f in fields(MCMCConfig))


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
    #: background (decision 0011). 3DGS-MCMC starts at a tenth or less of its cap.
    random_points: int | None = None
    #: random init: the points fill a cube of half-width random_extent x the scene extent
    #: around the point the cameras look at (``--strategy adc``: 0.27, 3DGS's Blender cube of
    #: +-1.3 on lego, whose extent is 4.89)
    random_extent: float = 0.5
    #: initial scale = init_scale x neighbour spacing (0: 0.1 for random init, 1 for SfM as DBS)
    init_scale: float = 0.0
    #: every primitive's opacity at the start (DBS / 3DGS-MCMC: 0.5; ``--strategy adc`` takes
    #: 3DGS's 0.1, see splatk.stages.fit_config)
    init_opacity: float = 0.5
    seed: int = 0
    lambda_dssim: float = 0.2
    opacity_reg: float = 0.01
    scale_reg: float = 0.01
    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh_degree_interval: int = 1000
    #: density control: mcmc (DBS: relocate, grow to ``budget``) | adc (3DGS: clone, split,
    #: prune, opacity reset; see splatk.train.strategies)
    strategy: str = "mcmc"
    #: MCMC's settings (refine_every / start / stop, noise_lr, split_scales, hold_growth ...);
    #: its cap is ``budget``
    mcmc: MCMCConfig = field(default_factory=MCMCConfig)
    #: ADC's settings (densify_from / until / every, opacity_reset_every, grad_threshold ...)
    adc: ADCConfig = field(default_factory=ADCConfig)
    #: multiplies every learning rate (primitives, colour, kernel networks); 1 = the defaults
    lr_scale: float = 1.0
    #: multiplies the log-scale learning rate alone. 0.005 is tuned for 30k iterations; short
    #: runs starve it (docs/decisions/0001-short-run-scaling.md), so short runs raise it
    scales_lr_mult: float = 1.0
    backend: str = "auto"
    device: str = "cpu"
    #: train views rendered per step; their losses are averaged. The learning rates rise by
    #: sqrt(batch_views) (Grendel-GS's rule for batched 3DGS training); 1 is the paper's setting
    batch_views: int = 1
    #: keep an in-memory snapshot this often for rollback (NaN or collapse)
    snapshot_every: int = 200
    #: roll back (as for a NaN) when the loss's running mean rises above this many times its
    #: lowest value: a run can collapse to an empty image without a NaN (decision 0005: cup,
    #: learning rates x10, loss 0.10 -> 0.66). Early collapses, whose lowest mean is
    #: still near the initial loss, are left to the START_LOSS_FACTOR test: 1.5 here caught them
    #: too, but also fired on healthy growth (bonsai, --budget auto, the 50k -> 100k stage: mean
    #: 0.065 vs lowest 0.043 while MCMC doubled the model, on both seeds). 0 turns every
    #: collapse check off.
    divergence_factor: float = 2.0
    #: every step renders on a random background colour, and RGBA train images are composited
    #: on the same colour (3DGS's --random_background), so that transparency is never free
    random_background: bool = False
    #: planar primitives: weight of 2DGS's normal consistency (2DGS: 0.05), the blended surfel
    #: normals against the normals of the rendered depth (train.planar_regularisers)
    normal_weight: float = 0.0
    #: ... on after this iteration (2DGS: 7000 of 30k; short runs scale it)
    normal_from: int = 7000
    #: planar primitives: weight of the depth distortion, the blended variance of inverse depth
    #: along each ray (2DGS: 0, 1000 on DTU, 10 or 100 on Tanks and Temples; its term is the
    #: L1 form, decision 0103)
    distortion_weight: float = 0.0
    #: ... on after this iteration (2DGS: 3000 of 30k; short runs scale it)
    distortion_from: int = 3000

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """From ``asdict`` output (config.yaml); MCMC settings at the top level, as older run
        folders recorded them, go to ``mcmc``."""
        d = dict(d)
        mcmc = dict(d.pop("mcmc", None) or {})
        mcmc.update({k: d.pop(k) for k in MCMC_FIELDS if k in d})
        # run folders written before it was on by default trained without it; a resume goes on so
        mcmc.setdefault("relocate_one_view", False)
        adc_settings = d.pop("adc", None) or {}
        return cls(mcmc=MCMCConfig(**mcmc), adc=ADCConfig(**adc_settings), **d)


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
    #: planar geometry terms (unweighted, mean over the step's views); None while a term is off
    normal_loss: float | None = None
    distortion_loss: float | None = None


class Trainer:
    """Trains ``model`` on ``scene``. ``backend``: the ops every step uses; default
    ``backends.get(config.backend, config.device)``, resolved here once (a benchmark may pass
    its own object). ``world``: this process's rank in a data-parallel job
    (:mod:`splatk.train.distributed`); it renders its share of each step's views."""

    def __init__(self, scene: Scene, model: SplatModel, config: TrainConfig, backend: Backend | None = None,
                 world: World = SINGLE):
        if world.size > config.batch_views:
            raise ValueError(f"{world.size} processes need at least as many views per step (batch_views "
                             f"{config.batch_views})")
        self.scene = scene
        self.cfg = config
        self.world = world
        #: bytes this rank sent into the last step's gradient all-reduce (0 in one process)
        self.sent_bytes = 0
        self.device = torch.device(config.device)
        self.backend = backends.get(config.backend, self.device) if backend is None else backend
        self.model = model.to(self.device)
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=self.device)
        self.extent = scene.extent
        self.it = 0
        self.elapsed = 0.0
        self.events: list[dict] = []
        self.lr_scale = 1.0  # halved by each rollback
        self.view_gen = torch.Generator().manual_seed(config.seed)
        self.mcmc_gen = torch.Generator(device=self.device).manual_seed(config.seed + 1)
        self.view_queue: list[int] = []
        self.strategy = make_strategy(config, scene, self.backend)
        self.geometry_terms = GeometryTerms(config.normal_weight, config.normal_from, config.distortion_weight,
                                            config.distortion_from)
        if (config.normal_weight > 0 or config.distortion_weight > 0) and getattr(model, "primitive", None) != "planar":
            raise ValueError("normal_weight and distortion_weight are terms of planar models")
        self.guard = Guard(self)
        self.build_optimizers()
        self.targets = [c.image_float(self.device) for c in scene.train]
        self.masks = [c.mask_float(self.device) for c in scene.train]  # None: every pixel counts

    # ---- optimisers and schedules ------------------------------------------------------
    def build_optimizers(self) -> None:
        lrs = self.model.learning_rates()
        lrs["means"] = self.cfg.means_lr * self.extent
        lrs["log_scales"] *= self.cfg.scales_lr_mult
        self.opt = PrimitiveAdam(self.model.prims, lrs)
        groups = [{"params": params, "lr": 0.0, "lr_mult": mult} for params, mult in self.model.kernel.network_groups()]
        self.net_opt = torch.optim.Adam(groups, lr=0.0) if groups else None

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
        if not self.view_queue:
            self.view_queue = torch.randperm(len(self.targets), generator=self.view_gen).tolist()
        return self.view_queue.pop()

    def _set_learning_rates(self, p: float) -> tuple[float, float]:
        """Every step size for progress ``p``; returns (means LR, the multiplier on all)."""
        # rollback halving x the configured multiplier x the batch's square-root rule
        lr_scale = self.lr_scale * self.cfg.lr_scale * math.sqrt(self.cfg.batch_views)
        means_lr = self.means_lr(p) * lr_scale
        self.opt.set_lr("means", means_lr)
        if lr_scale != 1.0:
            for name, lr in self.opt.base_lrs.items():
                if name != "means":
                    self.opt.set_lr(name, lr * lr_scale)
        if self.net_opt is not None:
            for g in self.net_opt.param_groups:
                g["lr"] = self.model.kernel.network_learning_rate(self.it, p) * g["lr_mult"] * lr_scale
        return means_lr, lr_scale

    # ---- one iteration -----------------------------------------------------------------
    def train_step(self) -> StepInfo:
        t0 = time.perf_counter()
        self.it += 1
        p = self.progress()
        means_lr, _ = self._set_learning_rates(p)
        views = [self._next_view() for _ in range(self.cfg.batch_views)]
        mine = my_share(views, self.world) if self.world.distributed else views
        # every rank draws the batch's backgrounds in the batch's order, so a random background
        # stays the one-process run's whatever share a rank renders
        drawn = [self._background_and_target(vi) for vi in views]
        renders, targets, photo_loss, terms, geo_sum = [], [], 0.0, {}, 0.0
        # planar models composite their geometry channels only while a geometry term is on
        geometry = {"geometry": True} if self.geometry_terms.wanted(self.it) else {}
        for vi in mine:
            background, target = drawn[views.index(vi)]
            cam = self.scene.train[vi]
            out = self.model.render(cam, background, sh_degree=self.sh_degree(), backend=self.backend, **geometry)
            photo_loss = photo_loss + photometric_loss(out.image, target, self.backend, self.cfg.lambda_dssim,
                                                       self.masks[vi])
            if geometry:
                geo_loss, values = self.geometry_terms(self.it, out.geometry, out.alpha, cam.K)
                photo_loss = photo_loss + geo_loss
                geo_sum = geo_sum + geo_loss.detach()
                for name, value in values.items():
                    terms[name] = terms.get(name, 0.0) + value.detach()
            renders.append(out)
            targets.append(target)
        if len(views) > 1:
            photo_loss = photo_loss / len(views)
        reg = regularisers(self.model, self.cfg.opacity_reg, self.cfg.scale_reg)
        with torch.no_grad():
            mse = sum(masked_mse(out.image.detach().clamp(0, 1), target, self.masks[vi])
                      for vi, out, target in zip(mine, renders, targets))
        if self.world.distributed:
            # the summed gradients are the one-process batch's: each rank adds 1/N of the
            # regularisers; the loss every rank judges (NaN, rollbacks) is the whole batch's
            loss = photo_loss + reg / self.world.size
            photo_sum, mse, geo_sum, *term_sums = self.world.sum_values(
                [photo_loss.detach(), mse, geo_sum, *terms.values()], self.device)
            terms = dict(zip(terms, term_sums))
            loss_value = photo_sum + float(reg.detach())
        else:
            loss = photo_loss + reg
            loss_value = float(loss.detach())
        # the guard judges the loss without the geometry terms: they start at a set iteration,
        # and the step up in the loss they bring then is no divergence
        guarded_value = loss_value - float(geo_sum) / len(views)
        if not math.isfinite(loss_value):
            event = self.guard.after_nan_loss()
        else:
            self.opt.zero_grad()
            if self.net_opt is not None:
                self.net_opt.zero_grad(set_to_none=True)
            loss.backward()
            before = statistics_before(self.strategy) if self.world.distributed else {}
            for vi, out in zip(mine, renders):
                self.strategy.observe(self.it, self.model, out, self.scene.train[vi])
            if self.world.distributed:
                self.world.observed(self.strategy, before, self.model.num_primitives, self.device)
                self.sent_bytes = self.world.sum_gradients(
                    list(self.model.prims.values()) + list(self.model.kernel.parameters()))
            self.opt.step()
            if self.net_opt is not None and any(g["lr"] > 0 for g in self.net_opt.param_groups):
                self.net_opt.step()
            with torch.no_grad():
                self.model.prims["quats"].data = torch.nn.functional.normalize(self.model.prims["quats"].data, dim=-1)
            event = self.guard.after_step(guarded_value)
            if event is None:
                self.strategy.step(self.it, p, self.model, self.opt, means_lr, self.mcmc_gen)
                if self.strategy.raised_loss():
                    self.guard.reset_loss_stats()  # the jump is the strategy's, not a divergence
                    # fit.json lists them, so a run shows its schedule (3DGS: every 3,000 iterations)
                    self.events.append({"iteration": self.it, "event": "opacity_reset",
                                        "message": f"iteration {self.it}: opacities reset to 0.01"})
                event = self._note_growth_held()
                self.guard.note_step()
        mse = mse / len(views)
        step_seconds = time.perf_counter() - t0
        # one clock for every rank: progress-based schedules and time budgets must agree
        self.elapsed += self.world.rank0_value(step_seconds, self.device) if self.world.distributed else step_seconds
        terms = {name: float(value) / len(views) for name, value in terms.items()}
        return StepInfo(
            self.it, self.cfg.iters, loss_value, -10 * math.log10(max(mse, 1e-10)),
            self.model.num_primitives, self.elapsed, self.progress(), event, **terms,
        )

    def _background_and_target(self, vi: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The background to render train view ``vi`` on and the image to compare with: the
        scene's, or (``random_background``) a colour drawn from the view generator (so that
        checkpoints resume it) with the view's alpha recomposited onto it."""
        if not self.cfg.random_background:
            return self.background, self.targets[vi]
        background = torch.rand(3, generator=self.view_gen).to(self.device)
        alpha = self.scene.train[vi].alpha_float(self.device)
        if alpha is None:
            return background, self.targets[vi]
        return background, self.targets[vi] + (background - self.background) * (1.0 - alpha)

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
        if self.guard.snapshot is None:  # a NaN before the first periodic snapshot goes back to here
            self.take_snapshot()
        while not self.done():
            info = self.train_step()
            if on_step:
                on_step(info)
            if on_checkpoint and self.it % checkpoint_every == 0:
                on_checkpoint(self)
            if should_stop and should_stop():
                break

    # ---- state ---------------------------------------------------------------------------
    def take_snapshot(self) -> None:
        """Make the current state the one a rollback returns to (e.g. after the model was
        compacted: going back to the full model would undo that)."""
        self.guard.snapshot = self.state_dict()

    def restore_last_healthy(self) -> None:
        """Go back to the last snapshot taken while training was healthy (keeping the clock and
        the event log), e.g. to checkpoint it when training stalls."""
        self.guard.restore_last_healthy()

    def state_dict(self) -> dict:
        return trainer_state(self)

    def load_state_dict(self, sd: dict) -> None:
        load_trainer_state(self, sd)
