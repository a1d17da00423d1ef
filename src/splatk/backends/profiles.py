"""Radial profiles as torch functions of the squared normalised radius (the specification
that native backends reproduce; see ``splatk.backends`` for the formulas)."""
from __future__ import annotations

import torch

from .types import GAUSSIAN_SUPPORT_SIGMAS, STUDENT_T_SUPPORT_SIGMAS


def evaluate_profile(kind: str, r2: torch.Tensor, params: torch.Tensor | None) -> torch.Tensor:
    """Profile value for each pair.

    Args:
        kind: profile kind.
        r2: [P] squared normalised radius in [0, 1).
        params: [P, n] per-pair profile parameters (already gathered per pair), or None.
    """
    if kind == "gaussian":
        return torch.exp(-0.5 * GAUSSIAN_SUPPORT_SIGMAS**2 * r2)
    if kind == "beta":
        beta = params[:, 0]
        # (1 - r2)^beta; r2 < 1 for every pair that reaches here.
        return torch.exp(beta * torch.log1p(-r2))
    if kind == "student_t":
        nu = params[:, 0]
        return torch.exp(-0.5 * (nu + 2.0) * torch.log1p(STUDENT_T_SUPPORT_SIGMAS**2 * r2 / nu))
    if kind == "table":
        k = params.shape[1]
        # r = sqrt(r2); the clamp keeps the sqrt's gradient finite at the exact centre.
        r = torch.sqrt(r2.clamp_min(1e-20))
        t = r * (k - 1)
        idx = torch.clamp(t.detach().floor().long(), 0, k - 2)
        lam = t - idx.to(t.dtype)
        d0 = params.gather(1, idx[:, None])[:, 0]
        d1 = params.gather(1, (idx + 1)[:, None])[:, 0]
        return (1.0 - lam) * d0 + lam * d1
    raise ValueError(f"unknown profile kind {kind!r}")
