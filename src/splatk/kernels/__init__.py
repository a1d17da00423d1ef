"""Splatting kernels, registered by name. Adding one touches one file (plus its import here)."""
from .base import KERNELS, Kernel, ViewContext, register_kernel
from . import gaussian, beta, student_t  # noqa: F401  (registration)

try:  # the learned kernel lives in its own module
    from . import learned  # noqa: F401
except ImportError:  # pragma: no cover - only while it is being written
    pass


def make_kernel(name: str, **options) -> Kernel:
    if name not in KERNELS:
        raise ValueError(f"unknown kernel {name!r}; choose from {', '.join(sorted(KERNELS))}")
    return KERNELS[name](**options)


__all__ = ["KERNELS", "Kernel", "ViewContext", "register_kernel", "make_kernel"]
