"""What image splats cost in bytes: the budget pays for everything needed to redraw the image.

Per-splat values are float32 for every kernel (equal terms), plus a learned splat's one-byte
turn and, with a shape palette, its one-byte palette index; what every splat shares (the learned
kernel's decoder and palette) is stored at float16. :mod:`splatk.image.file` writes exactly
these bytes after its header.
"""
from __future__ import annotations

import torch

from .kernels import LATENT_DIM, image_kernel

#: largest shape palette: its index is one byte per splat
MAX_SHAPES = 256
#: storage of the learned kernel's shared decoder and palette. Per-splat values stay float32 for
#: every kernel (equal terms); the shared part is a fixed cost that weighs most at small budgets
#: (at float32 the decoder and a 64-shape palette took 996 bytes, 12% of 8 KiB), and float16
#: keeps it to half. The fit rounds them at its end (:meth:`Splats2D.round_shared`), so the
#: image measured is the image stored.
SHARED_DTYPE = torch.float16
SHARED_BYTES_PER_FLOAT = torch.finfo(SHARED_DTYPE).bits // 8
#: floats of every splat: xy 2 + Cholesky 3 + colour 3
BASE_FLOATS = 8


def check_shapes(shapes: int) -> None:
    """ValueError unless ``shapes`` is a palette size a one-byte index reaches (0: none)."""
    if not 0 <= shapes <= MAX_SHAPES:
        raise ValueError(f"shapes must be 0 (a latent per splat) or 1 to {MAX_SHAPES} "
                         f"(a palette indexed by one byte), got {shapes}")


def floats_per_primitive(kernel: str, latent_dim: int = LATENT_DIM, shapes: int = 0) -> int:
    """Every per-primitive float: xy 2 + Cholesky 3 + colour 3 + the kernel's own (a learned
    kernel with a shape palette stores no latent per splat, only a byte: see bytes_per_primitive)."""
    return BASE_FLOATS + image_kernel(kernel).extra_floats(latent_dim, shapes)


def bytes_per_primitive(kernel: str, latent_dim: int = LATENT_DIM, shapes: int = 0) -> int:
    """float32 parameters, plus a learned kernel's one-byte turn and, with ``shapes``, its
    one-byte palette index."""
    check_shapes(shapes)
    return 4 * floats_per_primitive(kernel, latent_dim, shapes) + image_kernel(kernel).extra_bytes(shapes)


def network_bytes(kernel: str, latent_dim: int = LATENT_DIM, shapes: int = 0) -> int:
    """Bytes of what every splat shares, stored at float16 (:data:`SHARED_DTYPE`): the learned
    decoder and, with a shape palette, its ``shapes`` x ``latent_dim`` latents (0 for the other
    kernels)."""
    return SHARED_BYTES_PER_FLOAT * image_kernel(kernel).shared_floats(latent_dim, shapes)


def counted_network_bytes(kernel: str, latent_dim: int = LATENT_DIM, shapes: int = 0) -> int:
    """The part of :func:`network_bytes` the budget pays for: all of it, except for the paper's
    kernel, whose comparison counts the primitives only ("a similar memory footprint for
    primitives", paper Sec. 5)."""
    return network_bytes(kernel, latent_dim, shapes) if image_kernel(kernel).pays_shared else 0


def num_primitives(kernel: str, budget_bytes: int, latent_dim: int = LATENT_DIM, shapes: int = 0) -> int:
    """Primitives that fit in ``budget_bytes`` once the shared network is paid for (``splatk
    bench``'s rule too: budget = (budget_bytes - network_bytes) // bytes_per_primitive; the
    paper's kernel: budget_bytes // bytes_per_primitive)."""
    spare = int(budget_bytes) - counted_network_bytes(kernel, latent_dim, shapes)
    return max(0, spare) // bytes_per_primitive(kernel, latent_dim, shapes)
