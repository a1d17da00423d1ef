"""The 2D kernels of image splats, registered by name: ``k(u, v)`` over a splat's local
coordinates (the 3-sigma ellipse is the unit disk, see :mod:`splatk.image.model`).

``E(u, v) = exp(-4.5 (u^2 + v^2))`` is the Gaussian envelope:

* ``gaussian``: ``E``.                                                 8 floats / primitive
* ``gabor``:    ``E * prod_{d in u, v} sum_k a_{k,d} cos(pi f_{k,d} d)``, K = 2 waves per axis
  with learned amplitudes and frequencies (Gabor splatting, peers.md Sec. 7.3, which picks
  frequencies from a bank; here they are continuous parameters).     8 + 8 = 16 floats
* ``learned``:  ``E * Phi_dec_planar(u, v, z)`` with a per-primitive latent ``z`` (L values,
  default 2, ``latent_dim``) and one global decoder (paper Eq. 9; 3 linear layers, 8 wide, leaky
  ReLU), optionally with a shape palette and a turn per splat (:mod:`splatk.image.model`).
                                                                 8 + L floats + 1 byte

A kernel says what it adds to a splat (floats, bytes, shared floats), makes and trains its own
parameters on the model, and evaluates ``k(u, v)``; the order of :data:`KERNELS` is the kernel
code of the splat file (:mod:`splatk.image.file`).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..functional.planar import bilinear

#: support in sigmas (GaussianImage uses 3)
SUPPORT_SIGMAS = 3.0
LEAKY_SLOPE = 0.01
#: per-primitive latent floats of the learned kernel. Measured (kodim05 + kodim23, downscale 4,
#: 24 KiB, 200 iterations; docs/decisions/0008-image-learned-kernel.md): mean PSNR 23.89 dB at 10,
#: 25.10 at 4, 25.45 at 2, 25.73 at 1, 26.10 at 0 (gaussian 26.10): at equal bytes each latent
#: float costs primitives and pays back less. At 1000 iterations: 28.50 at 2, 28.45 at 1, 28.80
#: at 0 (gaussian 28.67). 2 is the best size that keeps a per-primitive shape; 0 shares one.
LATENT_DIM = 2
#: steps of a learned splat's turn over 2 pi: one byte
TURN_STEPS = 256
DEC_WIDTH = 8
GABOR_WAVES = 2


def envelope(uv: Tensor) -> Tensor:
    """``E(u, v)`` for samples ``uv`` [P, 2] -> [P] (0 outside the unit disk)."""
    r2 = (uv * uv).sum(-1)
    return torch.exp(-0.5 * SUPPORT_SIGMAS**2 * r2) * (r2 <= 1.0)


def decoder_floats(latent_dim: int = LATENT_DIM) -> int:
    """Floats of the shared Phi_dec_planar (paid once, out of the same byte budget)."""
    i, w = 2 + latent_dim, DEC_WIDTH
    return (i * w + w) + (w * w + w) + (w + 1)


class PlanarDecoder(nn.Module):
    """Phi_dec_planar(u, v, z) (paper Eq. 9): [2 + L] -> 8 -> 8 -> 1, leaky ReLU, signed output."""

    def __init__(self, latent_dim: int = LATENT_DIM, width: int = DEC_WIDTH):
        super().__init__()
        self.l1 = nn.Linear(2 + latent_dim, width)
        self.l2 = nn.Linear(width, width)
        self.l3 = nn.Linear(width, 1)
        for lin in (self.l1, self.l2):
            nn.init.kaiming_normal_(lin.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
            nn.init.zeros_(lin.bias)
        nn.init.zeros_(self.l3.weight)  # starts as the constant 1: the kernel is the Gaussian
        nn.init.ones_(self.l3.bias)

    def forward(self, uv: Tensor, z: Tensor) -> Tensor:
        """uv: [..., 2], z: [..., L] (broadcast) -> [...]. The z part of layer 1 is computed once."""
        h = F.linear(z, self.l1.weight[:, 2:], self.l1.bias) + F.linear(uv, self.l1.weight[:, :2])
        h = F.leaky_relu(h, LEAKY_SLOPE)
        h = F.leaky_relu(self.l2(h), LEAKY_SLOPE)
        return self.l3(h)[..., 0]


class ImageKernel:
    """Base class of the 2D kernels (the Gaussian's hooks: nothing beyond the envelope).

    ``model`` below is the :class:`~splatk.image.model.Splats2D` the kernel draws; its own
    parameters live on the model (they are the model's to save, move and train).
    """

    name = "base"

    def extra_floats(self, latent_dim: int, shapes: int) -> int:
        """float32 values per splat beyond xy 2 + Cholesky 3 + colour 3."""
        return 0

    def extra_bytes(self, shapes: int) -> int:
        """One-byte values per splat."""
        return 0

    def shared_floats(self, latent_dim: int, shapes: int) -> int:
        """Values every splat shares, stored at float16 (paid once out of the budget)."""
        return 0

    def init_params(self, model, n: int, latent_dim: int, generator: torch.Generator | None) -> None:
        """Make the kernel's parameters on ``model`` (after its geometry and colours)."""

    def param_groups(self, model, lr_kernel: float, lr_net: float) -> list[dict]:
        """Adam parameter groups of the kernel's parameters."""
        return []

    def extras(self, model) -> Tensor:
        """[N, E] the per-splat values packed for one gather (E may be 0)."""
        return model.chol.new_zeros(model.n, 0)

    def values(self, model, uv: Tensor, idx: Tensor, table: Tensor | None, extras: Tensor | None) -> Tensor:
        """k(u, v) for samples ``uv`` [P, 2] of splats ``idx`` [P] -> [P] (0 outside the disk);
        ``extras`` [P, E] are the gathered :meth:`extras` rows (None: gather them here)."""
        return envelope(uv)

    def native(self, model, table: Tensor | None) -> tuple[str, int, Tensor]:
        """(kind, aux, extras [N, E]) of the backend's ``render_image_splats``."""
        return self.name, 0, self.extras(model)


#: name -> kernel class, in the order of the splat file's kernel codes
IMAGE_KERNELS: dict[str, type[ImageKernel]] = {}


def register_image_kernel(cls: type[ImageKernel]) -> type[ImageKernel]:
    IMAGE_KERNELS[cls.name] = cls
    return cls


@register_image_kernel
class GaussianKernel2D(ImageKernel):
    """GaussianImage's kernel: the envelope alone."""

    name = "gaussian"


@register_image_kernel
class GaborKernel2D(ImageKernel):
    """The envelope times a sum of ``GABOR_WAVES`` cosines per axis (amplitudes, frequencies)."""

    name = "gabor"

    def extra_floats(self, latent_dim, shapes):
        return 4 * GABOR_WAVES

    def init_params(self, model, n, latent_dim, generator):
        amps = torch.zeros(n, 2, GABOR_WAVES)
        amps[..., 0] = 1.0  # first wave at frequency 0: starts as a Gaussian
        model.gabor_amps = nn.Parameter(amps)
        freqs = torch.zeros(n, 2, GABOR_WAVES)
        freqs[..., 1:] = 0.5 + 2.0 * torch.rand(n, 2, GABOR_WAVES - 1, generator=generator)
        model.gabor_freqs = nn.Parameter(freqs)

    def param_groups(self, model, lr_kernel, lr_net):
        return [{"params": [model.gabor_amps, model.gabor_freqs], "lr": lr_kernel}]

    def extras(self, model):
        return torch.cat([model.gabor_amps.reshape(model.n, -1), model.gabor_freqs.reshape(model.n, -1)], 1)

    def values(self, model, uv, idx, table, extras):
        env = envelope(uv)
        if extras is None:
            extras = self.extras(model)[idx]
        k = GABOR_WAVES
        a = extras[:, :2 * k].reshape(-1, 2, k)
        f = extras[:, 2 * k:].reshape(-1, 2, k)
        waves = (a * torch.cos(math.pi * f * uv[:, :, None])).sum(-1)  # [P, 2]
        return env * waves[:, 0] * waves[:, 1]

    def native(self, model, table):
        return self.name, GABOR_WAVES, self.extras(model)


@register_image_kernel
class LearnedKernel2D(ImageKernel):
    """The envelope times the shared decoder of each splat's latent at its turned (u, v); drawn
    from the per-splat table of decoder values (:meth:`Splats2D.kernel_table`) unless exact."""

    name = "learned"

    def extra_floats(self, latent_dim, shapes):
        return 0 if shapes else latent_dim  # a palette index is a byte, not a latent

    def extra_bytes(self, shapes):
        return 1 + (1 if shapes else 0)  # the turn, and the palette index

    def shared_floats(self, latent_dim, shapes):
        return decoder_floats(latent_dim) + shapes * latent_dim

    def init_params(self, model, n, latent_dim, generator):
        model.latents = nn.Parameter(0.1 * torch.randn(n, latent_dim, generator=generator))
        model.decoder = PlanarDecoder(latent_dim)
        model.turn = nn.Parameter(torch.rand(n, generator=generator) * (2.0 * math.pi))

    def param_groups(self, model, lr_kernel, lr_net):
        return [{"params": [model.latents, model.turn], "lr": lr_kernel},
                {"params": list(model.decoder.parameters()), "lr": lr_net}]

    def values(self, model, uv, idx, table, extras):
        env = envelope(uv)
        if model.exact or table is None:
            return env * model.decoder(model.turned_uv(uv, model.turns()[idx]), model.splat_latents(idx))
        return env * bilinear(table, idx, uv)

    def native(self, model, table):
        return "table", model.grid, table.reshape(model.n, -1)


#: the 2D kernel names (file order)
KERNELS = tuple(IMAGE_KERNELS)


def image_kernel(name: str) -> ImageKernel:
    """The registered 2D kernel ``name``; ValueError naming the choices for another name."""
    if name not in IMAGE_KERNELS:
        raise ValueError(f"unknown 2D kernel {name!r}; choose from {', '.join(KERNELS)}")
    return IMAGE_KERNELS[name]()
