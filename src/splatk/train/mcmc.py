"""MCMC density control as Deformable Beta Splatting does it (peers.md 1.4).

Every ``refine_every`` iterations inside the refine window: relocate dead primitives
(opacity <= 0.005) onto live ones sampled by opacity, grow by 5% up to the budget, and
perturb positions with opacity-gated noise shaped by each primitive's covariance.
Relocation only splits opacity, o' = 1 - (1 - o)^(1 / (N + 1)); scales are kept (DBS).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..functional.projection import covariances_3d
from .optim import PrimitiveAdam


@dataclass
class MCMCConfig:
    cap_max: int = 100_000
    refine_every: int = 100
    refine_start: int = 500
    #: refine until this fraction of training (DBS: 25k of 30k iterations)
    refine_stop: float = 25 / 30
    min_opacity: float = 0.005
    growth: float = 1.05
    noise_lr: float = 5e4


class MCMCStrategy:
    name = "mcmc"

    def __init__(self, config: MCMCConfig):
        self.cfg = config
        self.last_stats: dict = {}

    def is_refine_step(self, it: int, progress: float) -> bool:
        c = self.cfg
        return it % c.refine_every == 0 and it > c.refine_start and progress < c.refine_stop

    @torch.no_grad()
    def step(self, it: int, progress: float, model, opt: PrimitiveAdam, means_lr: float,
             generator: torch.Generator | None = None) -> None:
        if not self.is_refine_step(it, progress):
            return
        relocated = self.relocate(model, opt, generator)
        added = self.add(model, opt, generator)
        self.inject_noise(model, means_lr, generator)
        self.last_stats = {"relocated": relocated, "added": added, "num": model.num_primitives}

    def _split_opacity(self, model, sources: torch.Tensor) -> torch.Tensor:
        """New opacity of each sampled source given how often it was sampled (DBS rule)."""
        counts = torch.bincount(sources, minlength=model.num_primitives)[sources]
        o = model.opacities[sources]
        new_o = 1.0 - torch.pow(1.0 - o, 1.0 / (counts.to(o.dtype) + 1.0))
        eps = torch.finfo(o.dtype).eps
        return new_o.clamp(self.cfg.min_opacity, 1.0 - eps)

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
        alive = ~dead
        n_dead = int(dead.sum())
        if n_dead == 0 or int(alive.sum()) == 0:
            return 0
        dead_idx = torch.nonzero(dead).flatten()
        src = self._sample_sources(model, n_dead, alive, generator)
        new_logit = torch.logit(self._split_opacity(model, src))
        for name, p in model.prims.items():
            p.data[dead_idx] = p.data[src]
        model.prims["opacity_logits"].data[src] = new_logit
        model.prims["opacity_logits"].data[dead_idx] = new_logit
        opt.reset_moments(torch.cat([src, dead_idx]))
        return n_dead

    def add(self, model, opt: PrimitiveAdam, generator=None) -> int:
        n = model.num_primitives
        target = min(self.cfg.cap_max, int(self.cfg.growth * n))
        n_add = max(0, target - n)
        if n_add == 0:
            return 0
        alive = model.opacities > self.cfg.min_opacity
        if int(alive.sum()) == 0:
            return 0
        src = self._sample_sources(model, n_add, alive, generator)
        new_logit = torch.logit(self._split_opacity(model, src))
        model.prims["opacity_logits"].data[src] = new_logit
        opt.reset_moments(src)
        rows = {name: p.data[src].clone() for name, p in model.prims.items()}
        rows["opacity_logits"] = new_logit
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
