"""Adaptive density control as 3D Gaussian Splatting does it (Kerbl et al. 2023, Sec. 5.2).

While densifying (after ``densify_from`` and before ``densify_until`` iterations), every rendered
primitive accumulates the norm of its view-space position gradient (in normalised device
coordinates, as the 3DGS rasteriser reports it: the pixel-space gradient times half the image
size) and its largest screen radius. Every ``densify_every`` iterations:

* **clone** the primitives whose mean gradient reaches ``grad_threshold`` and whose largest
  scale is at most ``percent_dense`` x the scene extent (under-reconstructed: a copy joins them);
* **split** those above that size into ``split_copies`` primitives placed by sampling the
  primitive's own Gaussian, their scales divided by ``0.8 x split_copies`` (1.6), and remove the
  original (over-reconstructed);
* **prune** primitives with opacity below ``min_opacity``, and after the first opacity reset also
  those larger than ``max_screen_size`` pixels on screen or ``0.1`` x the extent in the world.

Every ``opacity_reset_every`` iterations the opacities are capped at 0.01, so that primitives the
views do not need fall below ``min_opacity`` and are pruned; on a white background once more at
``densify_from`` (3DGS with ``--white_background``, as it trains Blender scenes). Every row edit
(copy, remove) goes through :class:`~splatk.train.optim.PrimitiveAdam`, which keeps Adam's
moments in step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..functional.projection import quats_to_rotmats
from .optim import PrimitiveAdam
from .strategies import Strategy, register_strategy


@dataclass
class ADCConfig:
    """3DGS's defaults (its ``OptimizationParams``)."""

    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    opacity_reset_every: int = 3000
    #: mean norm of the view-space position gradient (NDC units) that marks a primitive for
    #: cloning or splitting
    grad_threshold: float = 2e-4
    #: clone below, split above this share of the scene extent (largest scale)
    percent_dense: float = 0.01
    min_opacity: float = 0.005
    #: pixels; applied once the opacity has been reset (3DGS: 20 after iteration 3000)
    max_screen_size: float = 20.0
    #: prune primitives whose largest scale exceeds this share of the scene extent
    max_world_size: float = 0.1
    split_copies: int = 2
    #: a cap on the primitive count (None: none, as 3DGS); clones and splits are skipped beyond it
    cap_max: int | None = None
    #: reset the opacities at ``densify_from`` too when training on a white background (3DGS's
    #: rule for its --white_background runs: the random init's floaters are white-on-white there)
    white_background_reset: bool = True


def screen_radii(conics: torch.Tensor, support_sigmas: float, gaussian_sigmas: float = 3.0) -> torch.Tensor:
    """[M] largest radius in pixels of each normalised conic's support ellipse (r2 < 1), scaled
    to 3 sigma as 3DGS measures it. ``conics``: [M, 3] (a, b, c) of the normalised inverse
    covariance."""
    a, b, c = conics.unbind(-1)
    # the smallest eigenvalue of the conic matrix is the largest of the covariance's inverse
    half_trace = 0.5 * (a + c)
    lam_min = half_trace - torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    radius = 1.0 / torch.sqrt(lam_min.clamp_min(1e-12))
    return radius * (gaussian_sigmas / support_sigmas)


@register_strategy
class ADCStrategy(Strategy):
    name = "adc"
    statistics = {"grad_sum": "sum", "seen": "sum", "max_radii": "max"}

    @classmethod
    def from_train_config(cls, config, scene, backend=None) -> "ADCStrategy":
        white = not config.random_background and all(float(c) == 1.0 for c in scene.background)
        return cls(config.adc, scene.extent, white_background=white)

    def __init__(self, config: ADCConfig, extent: float, white_background: bool = False):
        self.cfg = config
        self.extent = float(extent)
        self.white_background = white_background
        self.grad_sum: torch.Tensor | None = None
        self.seen: torch.Tensor | None = None
        self.max_radii: torch.Tensor | None = None
        self.last_stats: dict = {}

    # ---- statistics ---------------------------------------------------------------------
    def _ensure(self, n: int, device) -> None:
        if self.grad_sum is None or self.grad_sum.shape[0] != n:
            self.grad_sum = torch.zeros(n, device=device)
            self.seen = torch.zeros(n, device=device)
            self.max_radii = torch.zeros(n, device=device)

    def observe(self, it: int, model, render, camera) -> None:
        """The view-space gradients and screen radii of the primitives ``render`` drew."""
        if it >= self.cfg.densify_until or render.means2d is None or render.means2d.grad is None:
            return
        radii = screen_radii(render.conics.detach(), model.kernel.support_sigmas)
        self.accumulate(it, model.num_primitives, render.visible, render.means2d.grad, radii,
                        camera.width, camera.height)

    @torch.no_grad()
    def accumulate(self, it: int, n: int, visible: torch.Tensor, means2d_grad: torch.Tensor, radii: torch.Tensor,
                   width: int, height: int) -> None:
        """Accumulate one view's statistics (after its backward pass).

        Args:
            n: primitives in the model.
            visible: [M] indices of the rendered primitives.
            means2d_grad: [M, 2] gradient of the loss w.r.t. their pixel-space centres.
            radii: [M] their screen radii in pixels (:func:`screen_radii`).
        """
        if it >= self.cfg.densify_until:
            return
        self._ensure(n, means2d_grad.device)
        ndc = means2d_grad * torch.tensor([0.5 * width, 0.5 * height], device=means2d_grad.device)
        self.grad_sum.index_add_(0, visible, ndc.norm(dim=-1))
        self.seen.index_add_(0, visible, torch.ones_like(radii))
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radii)

    def state_dict(self) -> dict:
        if self.grad_sum is None:
            return {}
        return {"grad_sum": self.grad_sum.clone(), "seen": self.seen.clone(), "max_radii": self.max_radii.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.seen, self.max_radii = (
            (state["grad_sum"].clone(), state["seen"].clone(), state["max_radii"].clone()) if state else (None,) * 3)

    # ---- the step -----------------------------------------------------------------------
    def is_densify_step(self, it: int) -> bool:
        c = self.cfg
        return c.densify_from < it < c.densify_until and it % c.densify_every == 0

    @torch.no_grad()
    def step(self, it: int, progress: float, model, opt: PrimitiveAdam, means_lr: float = 0.0,
             generator: torch.Generator | None = None) -> None:
        """Densify and prune on densify steps; reset the opacities on reset steps."""
        c = self.cfg
        self.last_stats = {}
        if self.is_densify_step(it):
            self._ensure(model.num_primitives, model.prims["means"].device)
            cloned, split, pruned = self.densify_and_prune(model, opt, it, generator)
            self.last_stats = {"cloned": cloned, "split": split, "pruned": pruned, "num": model.num_primitives}
        white_reset = c.white_background_reset and self.white_background and it == c.densify_from
        if it < c.densify_until and (it % c.opacity_reset_every == 0 or white_reset):
            self.reset_opacity(model, opt)
            self.last_stats["opacity_reset"] = True

    def densify_and_prune(self, model, opt: PrimitiveAdam, it: int, generator=None) -> tuple[int, int, int]:
        c = self.cfg
        n = model.num_primitives
        grads = torch.nan_to_num(self.grad_sum / self.seen.clamp_min(1))
        size = model.scales.max(dim=-1).values
        hot = grads >= c.grad_threshold
        clone = hot & (size <= c.percent_dense * self.extent)
        split = hot & (size > c.percent_dense * self.extent)
        if c.cap_max is not None:  # keep within the cap: clones first, then splits, by gradient
            room = max(0, c.cap_max - n)
            clone = _top(clone, grads, room)
            split = _top(split, grads, max(0, room - int(clone.sum())) // max(1, c.split_copies - 1))
        n_clone, n_split = int(clone.sum()), int(split.sum())
        new_rows = {}
        if n_clone:
            new_rows = {k: p.data[clone].clone() for k, p in model.prims.items()}
        if n_split:
            split_rows = self._split_rows(model, split, generator)
            new_rows = {k: torch.cat([new_rows[k], v], 0) if k in new_rows else v for k, v in split_rows.items()}
        # prune: transparent, and after the first opacity reset too large on screen or in the world
        prune = model.opacities <= c.min_opacity
        if it > c.opacity_reset_every:
            prune |= (self.max_radii > c.max_screen_size) | (size > c.max_world_size * self.extent)
        prune |= split  # the split originals are replaced by their samples
        if new_rows:
            opt.append_rows(new_rows)
        keep = torch.cat([~prune, torch.ones(model.num_primitives - n, dtype=torch.bool, device=prune.device)])
        n_pruned = int((~keep).sum()) - n_split
        if not bool(keep.all()):
            opt.keep_rows(keep)
        self.grad_sum = self.seen = self.max_radii = None  # statistics start afresh
        return n_clone, n_split, n_pruned

    def _split_rows(self, model, split: torch.Tensor, generator=None) -> dict[str, torch.Tensor]:
        """``split_copies`` samples of each selected primitive's Gaussian, scales / (0.8 N)."""
        copies = self.cfg.split_copies
        means = model.prims["means"].data[split]
        scales = model.scales.data[split]
        rot = quats_to_rotmats(model.prims["quats"].data[split])
        noise = torch.randn(copies, *means.shape, generator=generator, device=means.device) * scales
        samples = torch.einsum("nij,cnj->cni", rot, noise) + means
        rows = {k: p.data[split].repeat(copies, *[1] * (p.dim() - 1)) for k, p in model.prims.items()}
        rows["means"] = samples.reshape(-1, 3)
        rows["log_scales"] = (model.prims["log_scales"].data[split] - math.log(0.8 * copies)).repeat(copies, 1)
        return rows

    def raised_loss(self) -> bool:
        return bool(self.last_stats.get("opacity_reset"))

    def reset_opacity(self, model, opt: PrimitiveAdam) -> None:
        """Cap every opacity at 0.01 and clear its Adam moments (3DGS ``reset_opacity``)."""
        logits = model.prims["opacity_logits"]
        cap = math.log(0.01 / 0.99)
        logits.data.clamp_(max=cap)
        opt.reset_moments_of("opacity_logits")


def _top(mask: torch.Tensor, score: torch.Tensor, k: int) -> torch.Tensor:
    """``mask`` restricted to its ``k`` highest-scoring entries."""
    if int(mask.sum()) <= k:
        return mask
    keep = torch.zeros_like(mask)
    idx = torch.nonzero(mask).flatten()
    keep[idx[score[idx].topk(k).indices]] = True
    return keep
