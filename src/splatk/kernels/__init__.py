"""Splatting kernels, registered by (primitive, name). Adding one touches one file (plus its
name in the import line below)."""
from .base import KERNELS, Kernel, ViewContext, kernel_names, make_kernel, register_kernel
from . import gaussian, beta, student_t, learned, planar, learned_planar  # noqa: F401  (registration)

__all__ = ["KERNELS", "Kernel", "ViewContext", "kernel_names", "make_kernel", "register_kernel"]
