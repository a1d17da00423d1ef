"""`splatk pretrain --kind planar`: fit the learned planar kernel to Gaussian surfels (paper Sec. 4.5).

As the volumetric pretraining (:mod:`splatk.stages.pretrain`): random camera-space primitives
(mu_cam, two scales, R_cam from :func:`splatk.stages.pretrain.random_views`), latent z = 0, He
init; here random (u, v) in [-1, 1]^2 and the target is the Gaussian surfel
``exp(-4.5 (u^2 + v^2))`` (3-sigma disk). Loss: binary cross-entropy between
sigmoid(Phi_dec_planar) and the target (the target is in [0, 1]); Adam, exponential decay.

Writes OUT (networks + options) and OUT.json (the same minus the networks, with the error).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..kernels.learned_planar import LearnedPlanarKernel, gaussian_surfel
from ..models.io import atomic_torch_save
from .pretrain import PretrainConfig, random_views

WEIGHTS_FORMAT = "splatk-learned-planar-kernel"


@dataclass
class PlanarPretrainConfig:
    """Settings of `splatk pretrain --kind planar`."""

    #: Adam steps
    steps: int = 1500
    #: random primitives per step
    batch: int = 256
    #: random (u, v) samples per primitive
    samples: int = 64
    #: Adam learning rate at the start; decays exponentially to lr_final
    lr: float = 3e-3
    lr_final: float = 3e-5
    #: random seed
    seed: int = 0
    #: held-out primitives for the final error
    eval_primitives: int = 2048


def _batch(kernel: LearnedPlanarKernel, n: int, p: int, gen: torch.Generator):
    view = random_views(n, PretrainConfig(), gen)
    z = torch.zeros(n, kernel.latent_dim)
    z_after = kernel.project(z, view.means_cam, view.scales[:, :2], view.rotmats_cam)
    uv = torch.rand(n, p, 2, generator=gen) * 2 - 1
    return kernel.logits(uv, z_after[:, None, :]), gaussian_surfel(uv)


def run_pretrain_planar(out: str | Path, cfg: PlanarPretrainConfig | None = None,
                        on_step: Callable[[int, int, float], None] | None = None,
                        overwrite: bool = False) -> Path:
    """Pretrain Phi_proj + Phi_dec_planar on Gaussian surfels; write OUT and OUT.json; return OUT."""
    cfg = cfg or PlanarPretrainConfig()
    if cfg.steps < 1:
        raise InputError(None, f"steps must be >= 1, got {cfg.steps}")
    out = Path(out)
    if out.exists() and not overwrite:
        raise InputError(out, "weights file exists", "pass --overwrite or choose another --out")
    torch.manual_seed(cfg.seed)
    kernel = LearnedPlanarKernel()
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    opt = torch.optim.Adam(kernel.parameters(), lr=cfg.lr)
    decay = math.log(cfg.lr_final / cfg.lr) / max(cfg.steps - 1, 1)
    t0 = time.perf_counter()
    loss_v = float("nan")
    for step in range(1, cfg.steps + 1):
        for g in opt.param_groups:
            g["lr"] = cfg.lr * math.exp(decay * (step - 1))
        logits, target = _batch(kernel, cfg.batch, cfg.samples, gen)
        loss = F.binary_cross_entropy_with_logits(logits, target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        loss_v = float(loss.detach())
        if on_step:
            on_step(step, cfg.steps, loss_v)
    with torch.no_grad():
        logits, target = _batch(kernel, cfg.eval_primitives, 64, torch.Generator().manual_seed(cfg.seed + 99))
        err = (torch.sigmoid(logits) - target).abs()
    meta = {"format": WEIGHTS_FORMAT, "version": 1, "target": "gaussian_surfel",
            "options": {"latent_dim": kernel.latent_dim, "latent2d_dim": kernel.latent2d_dim},
            "config": asdict(cfg), "final_loss": loss_v, "seconds": round(time.perf_counter() - t0, 2),
            "error": {"mae": float(err.mean()), "max_abs": float(err.max())}}
    state = {k: v.detach().clone() for k, v in kernel.state_dict().items()}
    atomic_torch_save({**meta, "state_dict": state}, out)
    out.with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
    return out


__all__ = ["PlanarPretrainConfig", "run_pretrain_planar", "WEIGHTS_FORMAT"]
