"""`splatk pretrain`: fit the learned kernel's networks to a target profile (paper Sec. 4.5).

Training data is synthetic: random camera-space primitives (mu_cam, s, R_cam) with z3d = 0, as
the paper says (no noise: with z3d = 0 the z3d columns of Phi_proj's first layer get no
gradient and keep their He init, so the latent still steers the kernel after pretraining),
and random radii r in [0, 1]; the loss is the mean squared error between Phi_dec(r^2, z2d) and
the target d(r):

* ``cosine``:     cos(pi/2 r^2)                       (the paper's choice and our default)
* ``gaussian``:   exp(-r^2 / (2 0.4^2)), shifted and rescaled so d(0) = 1 and d(1) = 0
* ``polynomial``: (1 - r^2)^2
* ``linear``:     1 - r

Writes OUT (the networks, the architecture options, target, error; loaded by
``LearnedKernel(weights=OUT)``) and OUT with suffix .json (the same minus the networks).
"""
from __future__ import annotations

import json
import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..kernels.base import ViewContext
from ..kernels.learned import ARCH_OPTIONS, WEIGHTS_FORMAT, LearnedKernel, phi_dec
from ..models.io import atomic_torch_save

GAUSSIAN_TARGET_SIGMA = 0.4


def target_profile(name: str, r: torch.Tensor) -> torch.Tensor:
    """Target d(r) for r in [0, 1] (see the module docstring)."""
    if name == "cosine":
        return torch.cos(0.5 * math.pi * r * r)
    if name == "gaussian":
        s2 = 2.0 * GAUSSIAN_TARGET_SIGMA**2
        tail = math.exp(-1.0 / s2)
        return (torch.exp(-r * r / s2) - tail) / (1.0 - tail)
    if name == "polynomial":
        return (1.0 - r * r) ** 2
    if name == "linear":
        return 1.0 - r
    raise ValueError(f"unknown pretraining target {name!r}; choose from {', '.join(TARGETS)}")


TARGETS = ("cosine", "gaussian", "polynomial", "linear")


@dataclass
class PretrainConfig:
    """Settings of `splatk pretrain`."""

    #: target profile: cosine | gaussian | polynomial | linear
    target: str = "cosine"
    #: joint optimisation steps of Phi_proj and Phi_dec (stage 2)
    steps: int = 800
    #: random primitives per step
    batch: int = 1024
    #: random radii per primitive (r = 0 and r = 1 always included)
    radii: int = 16
    #: stage-2 Adam learning rate at the start; decays exponentially to lr_final
    lr: float = 3e-3
    lr_final: float = 3e-5
    #: stage 1: candidate decoders trained side by side (the best one is kept)
    dec_candidates: int = 32
    #: stage 1: steps and Adam learning rate (decays 100x)
    dec_steps: int = 1500
    dec_lr: float = 2e-2
    #: stage 2 starts with Phi_proj's first-layer weights on mu, s, R scaled by this
    view_input_scale: float = 0.1
    #: torch threads while pretraining (the tensors are small; more threads mostly wait)
    threads: int = 1
    #: random seed (data and network init)
    seed: int = 0
    #: camera distance |mu_cam| is log-uniform in [exp(lo), exp(hi)] scene units
    log_dist_range: tuple[float, float] = (-3.0, 5.0)
    #: angular size s / |mu_cam| per axis is log-uniform in [exp(lo), exp(hi)]
    log_angle_range: tuple[float, float] = (-12.0, 0.0)
    #: |x / z| and |y / z| of mu_cam up to this (1.2: a 100 degree field of view, plus margin)
    max_tan: float = 1.2
    #: held-out primitives for the final error
    eval_primitives: int = 8192


def random_views(n: int, cfg: PretrainConfig, gen: torch.Generator) -> ViewContext:
    """n random camera-space primitives (paper Sec. 4.5: random mu_cam, s, R_cam)."""
    tan = (torch.rand(n, 2, generator=gen) * 2 - 1) * cfg.max_tan
    dirs = torch.cat([tan, torch.ones(n, 1)], 1)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    lo, hi = cfg.log_dist_range
    dist = torch.exp(lo + (hi - lo) * torch.rand(n, 1, generator=gen))
    lo, hi = cfg.log_angle_range
    scales = dist * torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=gen))
    from ..functional.projection import quats_to_rotmats

    R = quats_to_rotmats(torch.randn(n, 4, generator=gen))  # uniform on SO(3)
    return ViewContext(dirs * dist, scales, R)


def random_radii(n: int, p: int, gen: torch.Generator) -> torch.Tensor:
    """[n, p] radii: 0, 1, then p - 2 uniform in [0, 1]."""
    r = torch.rand(n, p, generator=gen)
    r[:, 0] = 0.0
    r[:, 1] = 1.0
    return r


@torch.no_grad()
def profile_error(kernel: LearnedKernel, target: str, cfg: PretrainConfig, seed: int) -> dict:
    """Error of Phi_dec against the target on fresh random primitives and radii."""
    gen = torch.Generator().manual_seed(seed)
    n = cfg.eval_primitives
    view = random_views(n, cfg, gen)
    z3d = torch.zeros(n, kernel.latent_dim) if "z" in kernel.inputs else None
    z2d = kernel.project(z3d, view)
    r = torch.rand(n, 64, generator=gen)
    err = (kernel.decode(z2d, r * r) - target_profile(target, r)).abs()
    ends = torch.tensor([0.0, 1.0])
    err_ends = (kernel.decode(z2d, ends * ends) - target_profile(target, ends)).abs()
    # error of the k-sample tables the rasteriser interpolates, at the sample radii
    return {
        "mae": float(err.mean()),
        "rmse": float(err.pow(2).mean().sqrt()),
        "max_abs": float(err.max()),
        "p99_abs": float(torch.quantile(err.flatten()[:1_000_000], 0.99)),
        "mae_r0": float(err_ends[:, 0].mean()),
        "mae_r1": float(err_ends[:, 1].mean()),
        "eval_samples": int(err.numel()),
    }


def _bce(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    # Cross-entropy against the soft target has its minimum where sigmoid(logits) = target,
    # like the squared error, but no sigmoid' factor in its gradient: the squared error
    # crawls where the profile must approach 0 or 1 (r = 1, r = 0).
    return F.binary_cross_entropy_with_logits(logits, target.clamp(0.0, 1.0))


def pretrain_decoder(kernel: LearnedKernel, cfg: PretrainConfig, gen: torch.Generator,
                     on_step=None) -> torch.Tensor:
    """Stage 1: fit Phi_dec(r^2, z2d) to the target with a free, constant z2d; returns z2d.

    A 4-wide leaky-ReLU decoder has few kinks and, from a plain He init, most runs end in a
    poor local minimum (a unit whose kink lies outside r^2 in [0, 1] is wasted; MAE ~0.02 and
    d(1) ~0.1 for the cosine). So ``dec_candidates`` decoders are trained side by side (one
    vmapped call) from He weights with the r^2 column scaled by 4 and the first-layer biases
    set to put each unit's kink at a random r^2 in (0.05, 0.95), and the one with the least
    mean + end-point error is kept (the end points are what k = 2 renders).
    """
    return _pretrain_decoder(kernel, cfg, gen, on_step)


@contextmanager
def _threads(n: int):
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _pretrain_decoder(kernel, cfg, gen, on_step):
    from torch.func import stack_module_state, vmap

    from ..kernels.learned import _mlp

    width, lat = kernel.dec_width, kernel.latent2d_dim
    decs = [_mlp([1 + lat, width, width, 1]) for _ in range(cfg.dec_candidates)]
    with torch.no_grad():
        for d in decs:
            w = d[0].weight
            w[:, 0] *= 4.0
            d[0].bias[:] = -w[:, 0] * (0.05 + 0.9 * torch.rand(width, generator=gen))
    stacked, _ = stack_module_state(decs)
    names = ("0.weight", "0.bias", "2.weight", "2.bias", "4.weight", "4.bias")
    params = [stacked[n] for n in names]
    z2d = torch.zeros(cfg.dec_candidates, 1, lat, requires_grad=True)
    r = torch.linspace(0.0, 1.0, 129)
    y = target_profile(cfg.target, r)
    run = vmap(lambda *a: phi_dec(*a, r * r, logits=True)[0])
    opt = torch.optim.Adam(params + [z2d], lr=cfg.dec_lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, 0.01 ** (1.0 / max(1, cfg.dec_steps)))
    for step in range(cfg.dec_steps):
        logits = run(*params, z2d)  # [C, P]
        loss = F.binary_cross_entropy_with_logits(logits, y.clamp(0, 1).expand_as(logits),
                                                  reduction="none").mean(1).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if on_step:
            on_step(step + 1, cfg.dec_steps + cfg.steps, float(loss.detach()) / cfg.dec_candidates)
    with torch.no_grad():
        err = (torch.sigmoid(run(*params, z2d)) - y).abs()
        best = int(torch.argmin(err.mean(1) + err[:, 0] + err[:, -1]))
        for module_name, p in zip(names, params):
            idx, attr = module_name.split(".")
            getattr(kernel.dec[int(idx)], attr).copy_(p[best])
    return z2d[best, 0].detach()


def pretrain_joint(kernel: LearnedKernel, cfg: PretrainConfig, gen: torch.Generator,
                   z2d_star: torch.Tensor, on_step=None) -> float:
    """Stage 2: Phi_proj and Phi_dec trained jointly on random primitives, z3d = 0 (paper
    Sec. 4.5).

    Phi_proj starts from He init with two changes: its first-layer weights on the view inputs
    (mu, s, R) are scaled by ``view_input_scale`` and its last bias is shifted so that its mean
    output is stage 1's z2d. The target ignores the view, so the network has to become
    nearly invariant to it. Starting near-invariant makes that reliable (cosine, seeds 0-2:
    MAE 0.0062-0.0068, max error < 0.05 with scale 0.1; MAE 0.0071-0.030, max error up to
    0.28 with plain He init) and leaves the He-scale weights on z3d (which get no gradient
    here, z3d being 0) in charge: a unit change of z3d moves the logits of d(0) + d(1) by
    1-2.5 after pretraining.
    """
    z3d = torch.zeros(cfg.batch, kernel.latent_dim) if "z" in kernel.inputs else None
    n_z = kernel.latent_dim if "z" in kernel.inputs else 0
    with torch.no_grad():
        kernel.proj[0].weight[:, n_z:] *= cfg.view_input_scale
        view = random_views(cfg.batch, cfg, gen)
        mean = kernel.project(z3d, view).mean(0)
        kernel.proj[-1].bias += z2d_star - mean
    opt = torch.optim.Adam(kernel.parameters(), lr=cfg.lr)
    decay = (cfg.lr_final / cfg.lr) ** (1.0 / max(1, cfg.steps - 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, decay)
    loss_val = float("nan")
    for step in range(1, cfg.steps + 1):
        view = random_views(cfg.batch, cfg, gen)
        r = random_radii(cfg.batch, cfg.radii, gen)
        logits = kernel.decode(kernel.project(z3d, view), r * r, logits=True)
        loss = _bce(logits, target_profile(cfg.target, r))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        loss_val = float(loss.detach())
        if on_step:
            on_step(cfg.dec_steps + step, cfg.dec_steps + cfg.steps, loss_val)
    return loss_val


def run_pretrain(
    target: str = "cosine",
    out: str | Path = "learned_cosine.pt",
    steps: int | None = None,
    seed: int | None = None,
    kernel_options: dict | None = None,
    on_step: Callable[[int, int, float], None] | None = None,
    overwrite: bool = False,
    config: PretrainConfig | None = None,
) -> Path:
    """Pretrain Phi_proj and Phi_dec on ``target``; write OUT and OUT.json; return OUT.

    Args:
        target: cosine | gaussian | polynomial | linear.
        out: weights file to write (``.pt``).
        steps, seed: override ``config``'s.
        kernel_options: architecture of the learned kernel (latent_dim, latent2d_dim,
            proj_width, dec_width, proj_inputs); others are ignored.
        on_step: called as ``on_step(step, total, loss)`` after every step of both stages
            (total = dec_steps + steps; loss is the cross-entropy).
        overwrite: replace an existing OUT.
        config: the remaining settings (defaults: :class:`PretrainConfig`).
    """
    cfg = PretrainConfig(**asdict(config)) if config else PretrainConfig()
    cfg.target = target
    if steps is not None:
        cfg.steps = int(steps)
    if seed is not None:
        cfg.seed = int(seed)
    if cfg.target not in TARGETS:
        raise InputError(None, f"unknown pretraining target {target!r}", f"choose from {', '.join(TARGETS)}")
    if cfg.steps < 1:
        raise InputError(None, f"steps must be >= 1, got {cfg.steps}")
    out = Path(out)
    meta_path = out.with_suffix(".json")
    if out.exists() and not overwrite:
        raise InputError(out, "weights file exists", "pass --overwrite or choose another --out")
    arch = {n: v for n, v in (kernel_options or {}).items() if n in ARCH_OPTIONS}

    torch.manual_seed(cfg.seed)  # network init (He, paper Sec. 4.5)
    kernel = LearnedKernel(weights="none", **arch)
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    t0 = time.perf_counter()
    with _threads(cfg.threads or torch.get_num_threads()):
        z2d_star = pretrain_decoder(kernel, cfg, gen, on_step)
        loss_val = pretrain_joint(kernel, cfg, gen, z2d_star, on_step)
    seconds = time.perf_counter() - t0
    error = profile_error(kernel, cfg.target, cfg, seed=cfg.seed + 1_000_003)
    options = kernel.arch_options()
    meta = {
        "format": WEIGHTS_FORMAT,
        "version": 1,
        "target": cfg.target,
        "options": options,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
        "error": error,
        "final_loss": loss_val,
        "seconds": round(seconds, 2),
        "threads": torch.get_num_threads(),
        "torch": str(torch.__version__),
    }
    state = {k: v.detach().clone() for k, v in kernel.state_dict().items()}
    atomic_torch_save({**meta, "state_dict": state}, out)
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return out


__all__ = ["PretrainConfig", "TARGETS", "run_pretrain", "target_profile", "profile_error"]
