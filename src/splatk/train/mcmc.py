"""MCMC density control as Deformable Beta Splatting does it (peers.md 1.4).

Every ``refine_every`` iterations inside the refine window: relocate dead primitives
(opacity <= 0.005) onto live ones sampled by opacity, grow by 5% up to the budget, and
perturb positions with opacity-gated noise shaped by each primitive's covariance.
Relocation splits opacity, o' = 1 - (1 - o)^(1 / N) for a source copied N - 1 times, and keeps
the scales (DBS, kernel-agnostic; ``split_scales: keep``, the default). ``split_scales: shrink``
also shrinks the copies' scales by 3DGS-MCMC's Eq. 9 (:func:`split_scale_factor`, derived for
Gaussians), so that the N stacked copies draw what the source drew instead of a fatter blob. Over
two seeds per scene (docs/decisions/0003-mcmc-split-scales-keep.md) its effect on test PSNR was
within the seed-to-seed spread, so the default stays DBS's.

Dead also counts, for a view-dependent kernel, a primitive that one train view draws while the
other train views that see it switch it off (``relocate_one_view``, on by default; not in DBS;
:mod:`splatk.train.view_support`, docs/decisions/0113).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional.projection import covariances_3d
from .optim import PrimitiveAdam
from .strategies import Strategy, register_strategy
from .view_support import one_view_primitives


@dataclass
class MCMCConfig:
    """Density-control settings (``TrainConfig.mcmc``; the cap is the run's budget)."""

    refine_every: int = 100
    refine_start: int = 500
    #: refine until this fraction of training (DBS: 25k of 30k iterations)
    refine_stop: float = 25 / 30
    min_opacity: float = 0.005
    growth: float = 1.05
    noise_lr: float = 5e4
    #: scales of split copies: keep (DBS) | shrink (3DGS-MCMC Eq. 9)
    split_scales: str = "keep"
    #: skip a refine step's growth while it found at least as many dead primitives as the growth
    #: would add (see :meth:`MCMCStrategy.step`)
    hold_growth: bool = True
    #: a view-dependent kernel's primitives that one train view draws and the others that see
    #: them switch off count as dead (:mod:`splatk.train.view_support`, docs/decisions/0113)
    relocate_one_view: bool = True


#: 3DGS-MCMC's binomial table stops at 51 copies (gsplat RelocationCUDA.cu n_max)
MAX_SPLIT_COPIES = 51


def split_scale_factor(opacity: torch.Tensor, new_opacity: torch.Tensor, copies: torch.Tensor) -> torch.Tensor:
    """3DGS-MCMC Eq. 9: the factor on the scales of ``copies`` stacked copies of a Gaussian of
    ``opacity`` that each get ``new_opacity``. Eq. 9's double sum over i and k collapses
    (hockey-stick identity) to o / sum_{j=1..N} C(N, j) (-1)^(j-1) o'^j / sqrt(j).
    float64: the alternating sum cancels for large N."""
    o, o_new = opacity.double(), new_opacity.double()
    n = copies.clamp(1, MAX_SPLIT_COPIES).double()
    j = torch.arange(1, MAX_SPLIT_COPIES + 1, dtype=torch.float64, device=o.device)
    log_binom = torch.lgamma(n[:, None] + 1) - torch.lgamma(j + 1) - torch.lgamma(n[:, None] - j + 1)
    terms = torch.exp(log_binom) * o_new[:, None] ** j / torch.sqrt(j)
    terms = torch.where(j <= n[:, None], terms, torch.zeros_like(terms))
    sign = torch.where(j % 2 == 1, 1.0, -1.0)
    denom = (terms * sign).sum(1)
    factor = o / denom
    # a cancelled sum (denom <= 0 in float64, never seen for N <= 51) keeps the scale
    return torch.where(torch.isfinite(factor) & (denom > 0), factor, torch.ones_like(factor)).to(opacity.dtype)


@register_strategy
class MCMCStrategy(Strategy):
    name = "mcmc"

    @classmethod
    def from_train_config(cls, config, scene, backend) -> "MCMCStrategy":
        return cls(config.mcmc, cap_max=config.budget, views=scene.train, backend=backend)

    def __init__(self, config: MCMCConfig, cap_max: int = 100_000, views=(), backend=None):
        # checked here, not at the first refine step hundreds of iterations into a run
        if config.split_scales not in ("keep", "shrink"):
            raise ValueError(f"split_scales must be keep or shrink, got {config.split_scales!r}")
        self.cfg = config
        #: the most primitives growth may reach (the run's budget; --budget auto moves it)
        self.cap_max = cap_max
        #: the train cameras and the ops that draw them, to find one-view primitives
        #: (``relocate_one_view``; a kernel whose profile does not depend on the view needs neither)
        self.views, self.backend = list(views), backend
        self.last_stats: dict = {}

    def is_refine_step(self, it: int, progress: float) -> bool:
        c = self.cfg
        return it % c.refine_every == 0 and it > c.refine_start and progress < c.refine_stop

    @torch.no_grad()
    def step(self, it: int, progress: float, model, opt: PrimitiveAdam, means_lr: float,
             generator: torch.Generator | None = None) -> None:
        """Relocate the dead, grow, add noise.

        With ``hold_growth``, a step that found at least as many dead primitives as it would add
        does not grow: the model is not using the capacity it has. Growing it anyway cascades when
        the budget far exceeds what the views can constrain: the dead share per step rises as each
        step splits live primitives into copies born near the dead threshold, and the model
        collapses (docs/decisions/0004-mcmc-hold-growth.md). While a model grows normally far
        fewer die per step than growth adds, but on tiny images the rule can leave a model below
        its budget.
        """
        if not self.is_refine_step(it, progress):
            return
        relocated = self.relocate(model, opt, generator)
        held = self.cfg.hold_growth and relocated >= self.growth_count(model.num_primitives) > 0
        added = 0 if held else self.add(model, opt, generator)
        self.inject_noise(model, means_lr, generator)
        self.last_stats = {"relocated": relocated, "added": added, "num": model.num_primitives,
                           "growth_held": held}

    def _split(self, model, sources: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(new opacity logit, new log-scales or None when scales are kept) of each sampled
        source, given how often it was sampled; the source and its copies all get them."""
        copies = torch.bincount(sources, minlength=model.num_primitives)[sources] + 1
        o = model.opacities[sources]
        new_o = 1.0 - torch.pow(1.0 - o, 1.0 / copies.to(o.dtype))
        eps = torch.finfo(o.dtype).eps
        new_o = new_o.clamp(self.cfg.min_opacity, 1.0 - eps)
        log_scales = None
        if self.cfg.split_scales == "shrink":
            factor = split_scale_factor(o, new_o, copies)
            log_scales = model.prims["log_scales"].data[sources] + torch.log(factor)[:, None]
        return torch.logit(new_o), log_scales

    def _sample_sources(self, model, n: int, alive: torch.Tensor, generator) -> torch.Tensor:
        probs = model.opacities.clone()
        probs[~alive] = 0
        probs = torch.nan_to_num(probs, nan=0.0).clamp_min(0)
        if probs.sum() <= 0:
            probs = alive.to(probs.dtype)
        return torch.multinomial(probs, n, replacement=True, generator=generator)

    def relocate(self, model, opt: PrimitiveAdam, generator=None) -> int:
        op = model.opacities
        finite = torch.stack([torch.isfinite(v).reshape(v.shape[0], -1).all(1) for v in model.prims.values()]).all(0)
        dead = (op <= self.cfg.min_opacity) | ~finite
        if self.cfg.relocate_one_view:
            dead |= one_view_primitives(model, self.backend, self.views)
        alive = ~dead
        n_dead = int(dead.sum())
        if n_dead == 0 or int(alive.sum()) == 0:
            return 0
        dead_idx = torch.nonzero(dead).flatten()
        src = self._sample_sources(model, n_dead, alive, generator)
        new_logit, new_log_scales = self._split(model, src)
        for name, p in model.prims.items():
            p.data[dead_idx] = p.data[src]
        for idx in (src, dead_idx):
            model.prims["opacity_logits"].data[idx] = new_logit
            if new_log_scales is not None:
                model.prims["log_scales"].data[idx] = new_log_scales
        opt.reset_moments(torch.cat([src, dead_idx]))
        return n_dead

    def growth_count(self, n: int) -> int:
        """How many primitives a growth step adds to a model of ``n``."""
        return max(0, min(self.cap_max, int(self.cfg.growth * n)) - n)

    def add(self, model, opt: PrimitiveAdam, generator=None) -> int:
        n_add = self.growth_count(model.num_primitives)
        if n_add == 0:
            return 0
        alive = model.opacities > self.cfg.min_opacity
        if int(alive.sum()) == 0:
            return 0
        src = self._sample_sources(model, n_add, alive, generator)
        new_logit, new_log_scales = self._split(model, src)
        model.prims["opacity_logits"].data[src] = new_logit
        if new_log_scales is not None:
            model.prims["log_scales"].data[src] = new_log_scales
        opt.reset_moments(src)
        rows = {name: p.data[src].clone() for name, p in model.prims.items()}
        opt.append_rows(rows)
        return n_add

    def inject_noise(self, model, means_lr: float, generator=None) -> None:
        # planar models have two scales; their scales_3d adds a zero along the disk's normal
        scales = model.scales_3d if hasattr(model, "scales_3d") else model.scales
        cov = covariances_3d(model.prims["quats"].data, scales.data)
        gate = torch.pow(1.0 - model.opacities, 100.0)
        noise = torch.randn(model.num_primitives, 3, generator=generator, device=cov.device)
        noise = noise * (gate * self.cfg.noise_lr * means_lr)[:, None]
        model.prims["means"].data += torch.bmm(cov, noise[:, :, None])[:, :, 0]
