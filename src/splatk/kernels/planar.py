"""Kernels of planar (surfel) primitives: what a :class:`~splatk.models.planar.PlanarModel` asks
of them is a :class:`~splatk.backends.PlanarProfile` for the visible splats of a view. They are
registered as ``("planar", name)`` (:func:`splatk.kernels.make_kernel` with ``primitive="planar"``).

* ``gaussian`` (here): the Gaussian surfel exp(-4.5 (u^2 + v^2)) over the 3-sigma disk (2DGS).
* ``learned``: :class:`~splatk.kernels.learned_planar.SurfelLearnedKernel` (Phi_proj +
  Phi_dec_planar, paper Sec. 4.4).

Volumetric-only kernels (beta, student_t) have no planar version; ``make_kernel`` says so by name.
"""
from __future__ import annotations

from ..backends import PlanarProfile
from .base import Kernel, ViewContext, register_kernel


class PlanarKernel(Kernel):
    """Base class of the planar kernels: the hooks of :class:`~splatk.kernels.base.Kernel`, with
    :meth:`profile` returning a :class:`~splatk.backends.PlanarProfile`."""

    primitive = "planar"
    #: (u, v) support in sigmas; both planar kernels end at the 3-sigma disk
    support_sigmas = 3.0

    @property
    def options(self) -> dict:
        return {}

    def profile(self, prims, view: ViewContext) -> PlanarProfile:
        raise NotImplementedError


@register_kernel
class SurfelGaussianKernel(PlanarKernel):
    """The Gaussian surfel (no parameters)."""

    name = "gaussian"

    def profile(self, prims, view):
        return PlanarProfile("gaussian_surfel")
