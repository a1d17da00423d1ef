"""Rasteriser backends: one fixed signature, a dict registry.

Every backend implements :func:`rasterize` with the same semantics (the pure-PyTorch
``torch`` backend is the specification; see ``docs/design.md``):

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

from typing import Callable, NamedTuple

import torch

GAUSSIAN_SUPPORT_SIGMAS = 3.0
STUDENT_T_SUPPORT_SIGMAS = 3.0
ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
TILE_SIZE = 16

PROFILE_KINDS = ("gaussian", "beta", "student_t", "table")


class Profile(NamedTuple):
    """Radial opacity profile handed to the rasteriser.

    Attributes:
        kind: one of ``PROFILE_KINDS``.
        params: ``None`` for gaussian; ``[N, 1]`` beta / nu; ``[N, k]`` table samples (k >= 2).
    """

    kind: str
    params: torch.Tensor | None = None


class RasterOutput(NamedTuple):
    """Rendered image.

    Attributes:
        colors: [H, W, C] composited colours (background included).
        alphas: [H, W, 1] accumulated opacity ``1 - T_final``.
    """

    colors: torch.Tensor
    alphas: torch.Tensor


RasterizeFn = Callable[..., RasterOutput]
_BACKENDS: dict[str, RasterizeFn] = {}
_AVAILABLE: dict[str, Callable[[], bool]] = {}


def register_backend(name: str, available: Callable[[], bool] = lambda: True):
    """Decorator: register ``fn`` as backend ``name``; ``available()`` says if it can run here."""

    def wrap(fn: RasterizeFn) -> RasterizeFn:
        _BACKENDS[name] = fn
        _AVAILABLE[name] = available
        return fn

    return wrap


def _load_all() -> None:
    # Importing registers; the native module compiles lazily on first use, not at import.
    from . import torch_ref  # noqa: F401

    try:
        from . import cpu_native  # noqa: F401
    except ImportError:
        pass


def backend_names() -> list[str]:
    _load_all()
    return sorted(_BACKENDS)


def is_available(name: str) -> bool:
    _load_all()
    return name in _AVAILABLE and _AVAILABLE[name]()


def resolve_backend(name: str, device: torch.device | str = "cpu") -> str:
    """Map ``auto`` to the fastest backend that runs on ``device``; check explicit names."""
    _load_all()
    device = torch.device(device)
    if name == "auto":
        if device.type == "cpu" and "cpu" in _BACKENDS and _AVAILABLE["cpu"]():
            return "cpu"
        return "torch"
    if name not in _BACKENDS:
        raise ValueError(f"unknown backend {name!r}; choose from {', '.join(backend_names())}, auto")
    if not _AVAILABLE[name]():
        from ..errors import BackendUnavailable

        raise BackendUnavailable(f"backend {name!r} is not available here")
    return name


def rasterize(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    profile: Profile,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    backend: str = "auto",
) -> RasterOutput:
    """Composite 2D splats into an image. Differentiable in every float input.

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
    name = resolve_backend(backend, means2d.device)
    if background is None:
        background = torch.zeros(colors.shape[1], device=colors.device, dtype=colors.dtype)
    if profile.kind not in PROFILE_KINDS:
        raise ValueError(f"unknown profile kind {profile.kind!r}")
    return _BACKENDS[name](
        means2d, conics, opacities, colors, depths, profile, int(width), int(height), background
    )
