"""Backends: the ops a render and a training step need, one object per implementation.

``get(name, device)`` returns a :class:`Backend` (``project``, ``sh_colors``, ``rasterize``,
``rasterize_planar``, ``ssim`` and optional native ops); the trainer and every stage resolve it
once and hand the object down, so models, kernels, colour models and losses never see a
backend's name. Backends register by name in a dict (``@register_backend("cpu")`` on the
class); ``auto`` is the available one with the highest ``priority`` for the device. The
pure-PyTorch ``torch`` backend is the specification (see ``docs/design.md``).

Every backend's :meth:`Backend.rasterize` has the same semantics:

* For pixel centre ``p`` (pixel (i, j) -> (i + 0.5, j + 0.5)) and primitive ``g``:
  ``d = p - means2d[g]``, ``r2 = a*dx*dx + 2*b*dx*dy + c*dy*dy`` with ``(a, b, c) = conics[g]``.
  Conics are *normalised*: the primitive's support (bounding ellipse) is ``r2 < 1``.
* ``alpha = min(0.999, opacities[g] * profile(r2))``; the pair is skipped when ``r2 >= 1`` or
  ``alpha < 1/255``.
* Primitives are composited front to back in order of ``depths`` (stable: ties by index).
  ``T`` starts at 1; a primitive whose ``T * (1 - alpha)`` would fall below ``1e-4`` ends the
  pixel and is not blended.  ``color = sum(colors[g] * alpha * T) + T_final * background``,
  ``alpha_out = 1 - T_final``.

Profiles (:class:`Profile`), all functions of the normalised radius ``r = sqrt(r2)`` in [0, 1]:

* ``gaussian``:  ``exp(-0.5 * S**2 * r2)`` with ``S = GAUSSIAN_SUPPORT_SIGMAS`` (support at 3 sigma).
* ``beta``:      ``(1 - r2) ** beta``, params ``[N, 1]`` = beta > 0 (DBS, support at 1 sigma).
* ``student_t``: ``(1 + S**2 * r2 / nu) ** (-(nu + 2) / 2)``, params ``[N, 1]`` = nu > 0, S = 3.
* ``table``:     ``k`` samples ``d_i`` at ``r_i = i / (k - 1)``, linear interpolation in ``r``
  (paper Sec. 4.3), params ``[N, k]``; gradients flow into the samples.
"""
from __future__ import annotations

import torch

from ..errors import BackendUnavailable
from .base import Backend
from .registry import BACKENDS as _BACKENDS
from .registry import register_backend
from .types import (ALPHA_MAX, ALPHA_MIN, GAUSSIAN_SUPPORT_SIGMAS, PLANAR_PROFILE_KINDS, PROFILE_KINDS,
                    STUDENT_T_SUPPORT_SIGMAS, T_MIN, TILE_SIZE, PlanarProfile, Profile, RasterOutput)


def _load_all() -> None:
    # Importing registers; the native module compiles lazily on first use, not at import.
    from . import cpu_backend, torch_backend, triton_backend  # noqa: F401


def backend_names() -> list[str]:
    _load_all()
    return sorted(_BACKENDS)


def is_available(name: str, device: torch.device | str = "cpu") -> bool:
    """Whether backend ``name`` runs on ``device`` here (the native one builds on this call)."""
    _load_all()
    return name in _BACKENDS and _BACKENDS[name].unavailable_reason(torch.device(device)) is None


def get(name: str, device: torch.device | str = "cpu") -> Backend:
    """The backend ``name`` (or ``auto``: the fastest that runs on ``device``) for ``device``.

    Raises:
        ValueError: an unknown name.
        splatk.errors.BackendUnavailable: the backend cannot run on ``device`` here.
    """
    _load_all()
    device = torch.device(device)
    if name == "auto":
        runnable = [c for c in _BACKENDS.values() if c.unavailable_reason(device) is None]
        return max(runnable, key=lambda c: c.priority)(device)
    if name not in _BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose from {', '.join(backend_names())}, auto")
    reason = _BACKENDS[name].unavailable_reason(device)
    if reason is not None:
        raise BackendUnavailable(f"backend {name!r} is not available here ({reason})")
    return _BACKENDS[name](device)


def resolve_backend(name: str, device: torch.device | str = "cpu") -> str:
    """The name ``get(name, device)`` resolves to (what rendered, for reports: never ``auto``)."""
    return get(name, device).name


def rasterize(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
              colors: torch.Tensor, depths: torch.Tensor, profile: Profile, width: int, height: int,
              background: torch.Tensor | None = None, backend: str = "auto") -> RasterOutput:
    """Composite 2D splats into an image with backend ``backend`` (a name; see
    :meth:`Backend.rasterize`). Differentiable in every float input.

    Args:
        means2d: [N, 2] pixel-space centres.
        conics: [N, 3] (a, b, c) of the normalised inverse covariance (support is r2 < 1).
        opacities: [N] in [0, 1].
        colors: [N, C] per-primitive colour (any C >= 1; extra channels e.g. depth).
        depths: [N] camera-space depth, sort key only (no gradient).
        profile: the radial profile and its per-primitive parameters.
        width, height: image size.
        background: [C] colour behind everything (zeros if None).
        backend: registered name or ``auto``.
    """
    if background is None:
        background = torch.zeros(colors.shape[1], device=colors.device, dtype=colors.dtype)
    if profile.kind not in PROFILE_KINDS:
        raise ValueError(f"unknown profile kind {profile.kind!r}")
    return get(backend, means2d.device).rasterize(means2d, conics, opacities, colors, depths, profile,
                                                  int(width), int(height), background)


__all__ = [
    "ALPHA_MAX", "ALPHA_MIN", "GAUSSIAN_SUPPORT_SIGMAS", "PLANAR_PROFILE_KINDS", "PROFILE_KINDS",
    "STUDENT_T_SUPPORT_SIGMAS", "T_MIN", "TILE_SIZE", "Backend", "PlanarProfile", "Profile",
    "RasterOutput", "backend_names", "get", "is_available", "register_backend", "resolve_backend",
    "rasterize",
]
