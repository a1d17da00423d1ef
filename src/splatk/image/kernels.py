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

* ``gabsplat``: GabSplat, the Gabor splatting baseline the paper compares against (Wurster et
  al. 2024; peers.md Sec. 7.3) in its own rotation-scale geometry (:class:`GabSplatKernel2D`).
                                                    8 + 2 K floats + 2 K bytes (K = 2 per axis)
* ``learned-paper``: the paper's planar learned kernel as published, ``k = sigmoid(Phi_dec_planar(
  u, v, z))`` inside the unit disk, a 10-float latent per splat, no envelope, turn or palette; the
  budget counts the primitives only, as the paper's "memory footprint for primitives" does
  (``splatk image --mode paper``).                                  8 + 10 floats

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
#: per-primitive latent floats of the learned kernel: at equal bytes each latent float costs
#: primitives and pays back less (docs/decisions/0008-image-learned-kernel.md); 2 is the best
#: size that keeps a per-primitive shape; 0 shares one.
LATENT_DIM = 2
#: steps of a learned splat's turn over 2 pi: one byte
TURN_STEPS = 256
DEC_WIDTH = 8
GABOR_WAVES = 2
#: the paper's planar latent size ("a 10D latent code", paper Sec. 4.4)
PAPER_LATENT_DIM = 10
#: Adam steps and samples of the paper kernel's pretraining on the Gaussian surfel (paper Sec. 4.5)
PRETRAIN_STEPS = 300
PRETRAIN_SAMPLES = 1024
#: GabSplat: frequencies in the bank (f_j = j GABSPLAT_FREQ_STEP radians per sigma, j < BANK;
#: an index is one byte), waves kept per axis, random extra waves while exploring, the share of
#: the fit that explores, and the weight of the coefficients' L1 term (peers.md Sec. 7.3).
#: GabSplat's code sets the bank's top frequency per image (128 and 1024 radians per sigma for
#: its large images); a wave of f radians per sigma aliases past f = pi sigma_px, so on splats of
#: 2 to 6 px the bank stops at 15 (with 128, fits picked aliased waves near 100: noise;
#: docs/decisions/0012-image-gabsplat.md)
GABSPLAT_BANK = 16
GABSPLAT_FREQ_STEP = 1.0
GABSPLAT_TOP = 2
GABSPLAT_RANDOM = 2
GABSPLAT_EXPLORE = 0.8
GABSPLAT_L1 = 1e-4


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
    #: whether ``splatk image --kernel`` offers it (the paper kernel is chosen by ``--mode paper``)
    choosable = True
    #: whether the backends' native ``render_image_splats`` draws it (else the torch path does)
    has_native = True
    #: whether it has a shared decoder (``model.decoder``, stored at float16, latents per splat)
    decoded = False
    #: whether the budget pays for the shared floats too (the paper counts primitives only)
    pays_shared = True

    def init_geometry(self, model, n: int, s0: float) -> None:
        """Make the splats' shape parameters: the Cholesky factor in pixels (GaussianImage)."""
        model.chol = nn.Parameter(torch.tensor([s0, 0.0, s0]).repeat(n, 1))  # l11, l21, l22 (px)

    def chol_factors(self, model) -> tuple[Tensor, Tensor, Tensor]:
        """l11, l21, l22 with the diagonal kept >= 0.3 px (no degenerate splats)."""
        c = model.chol
        return c[:, 0].abs() + 0.3, c[:, 1], c[:, 2].abs() + 0.3

    def geometry_groups(self, model, lr_shape: float, lr_kernel: float) -> list[dict]:
        """Adam parameter groups of the shape parameters (``lr_shape`` is in pixels)."""
        return [{"params": [model.chol], "lr": lr_shape}]

    def prepare(self, model, generator: torch.Generator | None) -> None:
        """Ready a new model for fitting (pretraining); not run when a file is loaded."""

    def before_step(self, model, frac: float, generator: torch.Generator | None) -> None:
        """Called before each fit iteration at ``frac`` = (iteration - 1) / iterations."""

    def regularization(self, model) -> Tensor | float:
        """A term added to the fit's loss."""
        return 0.0

    def table(self, model) -> Tensor | None:
        """[N, G, G] the per-splat table the render samples (None: no table)."""
        return None

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
    decoded = True

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

    def table(self, model):
        return None if model.exact else model.kernel_table()

    def values(self, model, uv, idx, table, extras):
        env = envelope(uv)
        if model.exact or table is None:
            return env * model.decoder(model.turned_uv(uv, model.turns()[idx]), model.splat_latents(idx))
        return env * bilinear(table, idx, uv)

    def native(self, model, table):
        return "table", model.grid, table.reshape(model.n, -1)


def disk(uv: Tensor) -> Tensor:
    """1 inside the unit disk (the splat's 3-sigma ellipse), 0 outside: uv [P, 2] -> [P]."""
    return ((uv * uv).sum(-1) <= 1.0).to(uv.dtype)


def pretrain_gaussian(decoder: nn.Module, latent_dim: int, generator: torch.Generator | None) -> None:
    """Fit ``sigmoid(decoder(u, v, 0))`` to the Gaussian surfel ``exp(-4.5 r^2)`` on the unit disk
    (paper Sec. 4.5: the planar decoder is pretrained on 2D Gaussian surfels, latents at 0)."""
    uv = torch.rand(PRETRAIN_SAMPLES, 2, generator=generator) * 2.0 - 1.0
    uv = uv[(uv * uv).sum(-1) <= 1.0]
    target = envelope(uv)
    z = uv.new_zeros(uv.shape[0], latent_dim)
    opt = torch.optim.Adam(decoder.parameters(), lr=1e-2)
    for _ in range(PRETRAIN_STEPS):
        loss = ((torch.sigmoid(decoder(uv, z)) - target) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


@register_image_kernel
class PaperLearnedKernel2D(ImageKernel):
    """The paper's planar kernel: ``sigmoid(Phi_dec_planar(u, v, z))`` on the unit disk (paper Eq. 9,
    a sigmoid output as the volumetric decoder's), a latent per splat, drawn from the per-splat
    table unless exact. The budget pays for the primitives only (the paper compares "a similar
    memory footprint for primitives"); the file still stores the decoder, at float16."""

    name = "learned-paper"
    choosable = False
    has_native = False  # the native table kind multiplies by the Gaussian envelope
    decoded = True
    pays_shared = False

    def extra_floats(self, latent_dim, shapes):
        return latent_dim

    def shared_floats(self, latent_dim, shapes):
        return decoder_floats(latent_dim)

    def init_params(self, model, n, latent_dim, generator):
        model.latents = nn.Parameter(torch.zeros(n, latent_dim))  # all zeros, as the paper's z
        model.decoder = PlanarDecoder(latent_dim)
        nn.init.kaiming_normal_(model.decoder.l3.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")

    def prepare(self, model, generator):
        pretrain_gaussian(model.decoder, model.latent_dim, generator)

    def param_groups(self, model, lr_kernel, lr_net):
        return [{"params": [model.latents], "lr": lr_kernel},
                {"params": list(model.decoder.parameters()), "lr": lr_net}]

    def table(self, model):
        if model.exact:
            return None
        g = torch.linspace(-1.0, 1.0, model.grid, dtype=model.latents.dtype, device=model.latents.device)
        vv, uu = torch.meshgrid(g, g, indexing="ij")
        uv = torch.stack([uu, vv], -1).reshape(1, -1, 2)
        out = torch.sigmoid(model.decoder(uv, model.latents[:, None, :]))
        return out.reshape(model.n, model.grid, model.grid)

    def values(self, model, uv, idx, table, extras):
        if model.exact or table is None:
            return disk(uv) * torch.sigmoid(model.decoder(uv, model.latents[idx]))
        return disk(uv) * bilinear(table, idx, uv)


class _WaveProduct(torch.autograd.Function):
    """``prod_d sum_j a_{j,d} cos(f_{j,d} t_d)`` for t [P, 2], a and f [P, 2, M] -> [P], with a
    hand-written backward (autograd's graph of the same keeps five [P, 2, M] tensors per pass);
    ``f`` are the bank indices (no gradient; a frequency is its index times GABSPLAT_FREQ_STEP)."""

    @staticmethod
    def forward(ctx, t, a, f):
        ft = f * GABSPLAT_FREQ_STEP * t[:, :, None]
        cos = torch.cos(ft)
        sums = (a * cos).sum(-1)  # [P, 2]
        ctx.save_for_backward(t, a, f, cos, sums)
        return sums[:, 0] * sums[:, 1]

    @staticmethod
    def backward(ctx, v_w):
        t, a, f, cos, sums = ctx.saved_tensors
        v_sums = v_w[:, None] * sums.flip(1)  # d(s0 s1)/d s0 = s1, and the other way
        v_a = v_sums[:, :, None] * cos
        fs = f * GABSPLAT_FREQ_STEP
        v_t = -v_sums * (a * fs * torch.sin(fs * t[:, :, None])).sum(-1)
        return v_t, v_a, None


@register_image_kernel
class GabSplatKernel2D(ImageKernel):
    """GabSplat (Gabor splatting, Wurster et al. 2024; peers.md Sec. 7.3) for summed images.

    Geometry is rotation-scale, as GabSplat's: sigmas ``s`` [N, 2] (px) and an angle ``theta``,
    so the waves run along the ellipse's own axes. With ``t = S R (x - mu)`` (S = diag(1 / s),
    pixel offsets into the ellipse's frame, in sigmas)::

        k = exp(-|t|^2 / 2) * prod_{d in 1, 2} sum_{j in top K} a_{j,d} cos(f_j t_d),   f_j = j

    over a bank of :data:`GABSPLAT_BANK` frequencies ``f_j = j`` (``max_frequency * j /
    num_frequencies`` with GabSplat's defaults, max_frequency = num_frequencies), cut at 3 sigma.
    Every splat trains a coefficient for every bank frequency and axis; each step draws the
    :data:`GABSPLAT_TOP` largest per axis plus :data:`GABSPLAT_RANDOM` random others (GabSplat's
    top-2 + 2 random), the random ones only for the first :data:`GABSPLAT_EXPLORE` of the fit so
    the image trained last is the one stored. Loss term: ``1e-4 mean |a|`` (GabSplat's).
    Stored per splat: xy 2, sigmas 2, angle 1, colour 3, the top K coefficients per axis (float32)
    and their bank indices (a byte each).
    """

    name = "gabsplat"
    has_native = False

    def extra_floats(self, latent_dim, shapes):
        return 2 * GABSPLAT_TOP

    def extra_bytes(self, shapes):
        return 2 * GABSPLAT_TOP

    def init_geometry(self, model, n, s0):
        model.sigmas = nn.Parameter(torch.full((n, 2), s0))
        model.angle = nn.Parameter(torch.zeros(n))

    def chol_factors(self, model):
        s1, s2 = model.sigmas[:, 0].abs() + 0.3, model.sigmas[:, 1].abs() + 0.3
        c, s = torch.cos(model.angle), torch.sin(model.angle)
        # Sigma = R^T diag(s1^2, s2^2) R with R's rows (c, s) and (-s, c); its Cholesky factor
        sxx = c * c * s1 * s1 + s * s * s2 * s2
        sxy = c * s * (s1 * s1 - s2 * s2)
        l11 = torch.sqrt(sxx)
        return l11, sxy / l11, s1 * s2 / l11

    def geometry_groups(self, model, lr_shape, lr_kernel):
        return [{"params": [model.sigmas], "lr": lr_shape}, {"params": [model.angle], "lr": lr_kernel}]

    def param_groups(self, model, lr_kernel, lr_net):
        return [{"params": [model.wave_coeffs], "lr": lr_kernel}]

    def init_params(self, model, n, latent_dim, generator):
        # frequency 0 at weight 1, the rest 0: the splat starts as the Gaussian, as every kernel here
        # (GabSplat draws 0.1 N(0, 1) for all, which did worse: docs/decisions/0012-image-gabsplat.md)
        coeffs = torch.zeros(n, 2, GABSPLAT_BANK)
        coeffs[..., 0] = 1.0
        model.wave_coeffs = nn.Parameter(coeffs)
        model.wave_random = None  # [N, 2, R] this step's random picks while exploring

    def before_step(self, model, frac, generator):
        if frac >= GABSPLAT_EXPLORE or GABSPLAT_RANDOM == 0:
            model.wave_random = None
            return
        # R distinct picks among the frequencies outside each axis's top K
        scores = torch.rand(model.wave_coeffs.shape, generator=generator).to(model.wave_coeffs.device)
        scores.scatter_(2, self.top(model), -1.0)
        model.wave_random = scores.topk(GABSPLAT_RANDOM, dim=2).indices

    @staticmethod
    def top(model) -> Tensor:
        """[N, 2, K] bank indices of each axis's K largest |coefficients| (what is stored)."""
        return model.wave_coeffs.detach().abs().topk(GABSPLAT_TOP, dim=2).indices

    def picked(self, model) -> Tensor:
        """[N, 2, M] the bank indices drawn this step (top K, and the random ones while exploring)."""
        top = self.top(model)
        return top if model.wave_random is None else torch.cat([top, model.wave_random], 2)

    def regularization(self, model):
        return GABSPLAT_L1 * model.wave_coeffs.abs().mean()

    def extras(self, model):
        l11, l21, l22 = self.chol_factors(model)
        s1, s2 = model.sigmas[:, 0].abs() + 0.3, model.sigmas[:, 1].abs() + 0.3
        c, s = torch.cos(model.angle), torch.sin(model.angle)
        # t = S R (x - mu) with x - mu = 3 L (u, v): Q = 3 S R L, row by row
        q = 3.0 * torch.stack([(c * l11 + s * l21) / s1, s * l22 / s1,
                               (-s * l11 + c * l21) / s2, c * l22 / s2], 1)
        idx = self.picked(model)
        coeffs = model.wave_coeffs.gather(2, idx)
        return torch.cat([q, coeffs.reshape(model.n, -1), idx.to(q.dtype).reshape(model.n, -1)], 1)

    def values(self, model, uv, idx, table, extras):
        if extras is None:
            extras = self.extras(model)[idx]
        m = (extras.shape[1] - 4) // 4
        q, a, f = extras.split([4, 2 * m, 2 * m], 1)
        t = (q.reshape(-1, 2, 2) * uv[:, None, :]).sum(-1)  # [P, 2] = Q (u, v)
        return envelope(uv) * _WaveProduct.apply(t, a.reshape(-1, 2, m), f.detach().reshape(-1, 2, m))


#: the 2D kernel names (file order)
KERNELS = tuple(IMAGE_KERNELS)
#: the kernels `splatk image --kernel` offers
KERNEL_CHOICES = tuple(k for k, cls in IMAGE_KERNELS.items() if cls.choosable)


def image_kernel(name: str) -> ImageKernel:
    """The registered 2D kernel ``name``; ValueError naming the choices for another name."""
    if name not in IMAGE_KERNELS:
        raise ValueError(f"unknown 2D kernel {name!r}; choose from {', '.join(KERNELS)}")
    return IMAGE_KERNELS[name]()
