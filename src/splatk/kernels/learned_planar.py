"""The learned planar kernel (paper Sec. 4.4, Eq. 9); the Gaussian surfel baseline it is pretrained
towards is :func:`splatk.functional.planar.gaussian_surfel`.

A planar primitive (2DGS-style disk, see :mod:`splatk.backends.planar_torch`) carries a latent
``z`` [N, latent_dim] (10 values). Per view, Phi_proj of the volumetric architecture (4 linear
layers, 64 wide, leaky ReLU; inputs encoded as in :mod:`splatk.kernels.learned`, with the two
planar scales) maps it to ``z_after`` and the planar decoder gives a *general* (not radially
symmetric) kernel over the disk's local coordinates::

    d = sigmoid(Phi_dec_planar(u, v, z_after))        # 3 linear layers, 8 wide (paper Eq. 9)

(u, v) in [-1, 1]^2 spans the disk's 3-sigma square; the support is the unit disk. The output
keeps the paper's sigmoid: in 3D the kernel is an opacity that is alpha-composited, so it must
lie in [0, 1] (the signed output of :mod:`splatk.image.kernels` is for summed images only).

Rasterisers do not call the decoder per pixel: :meth:`LearnedPlanarKernel.table` samples it on
a ``G x G`` grid of nodes per primitive and view, and pixels interpolate bilinearly
(:func:`splatk.functional.planar.bilinear`); :meth:`LearnedPlanarKernel.exact` is the reference.
Pretraining (Gaussian surfel target, paper Sec. 4.5) is in :mod:`splatk.stages.pretrain_planar`.

:class:`SurfelLearnedKernel` is the kernel a planar model draws with (registered as
``("planar", "learned")``): the network plus per-primitive latents, schedules and weights.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..backends import PlanarProfile
from ..functional.planar import SURFEL_SUPPORT_SIGMAS, bilinear, gaussian_surfel
from .base import read_weights_file, register_kernel, scale_learned_options
from .learned import LEAKY_SLOPE, LOG_ANGLE_SCALE, LOG_ANGLE_SHIFT, LOG_DIST_SCALE, _he_init, _mlp
from .planar import PlanarKernel

SUPPORT_SIGMAS = SURFEL_SUPPORT_SIGMAS
#: weights made by ``splatk pretrain --kind planar --steps 10000 --out src/splatk/assets/learned_planar.pt``
#: (Gaussian-surfel target; mean abs error 0.015, see learned_planar.json; 1500 steps gave 0.09)
DEFAULT_PLANAR_WEIGHTS = Path(__file__).resolve().parent.parent / "assets" / "learned_planar.pt"
PLANAR_WEIGHTS_FORMAT = "splatk-learned-planar-kernel"  # stages.pretrain_planar.WEIGHTS_FORMAT


class LearnedPlanarKernel(nn.Module):
    """Phi_proj (volumetric architecture) + Phi_dec_planar (width 8, sigmoid).

    Args:
        latent_dim: size of the per-primitive latent z (10).
        latent2d_dim: size of z_after (10).
        proj_width: Phi_proj hidden width (64).
        dec_width: Phi_dec_planar hidden width (8, paper Sec. 4.4).
        grid: table nodes per axis.
    """

    name = "learned_planar"

    def __init__(self, latent_dim: int = 10, latent2d_dim: int = 10, proj_width: int = 64,
                 dec_width: int = 8, grid: int = 8):
        super().__init__()
        self.latent_dim, self.latent2d_dim, self.grid = int(latent_dim), int(latent2d_dim), int(grid)
        in_dim = self.latent_dim + 4 + 2 + 9  # z, (dir, log dist), log angular scales (2), R_cam
        w = int(proj_width)
        self.proj = _mlp([in_dim, w, w, w, self.latent2d_dim])
        self.dec = _mlp([2 + self.latent2d_dim, int(dec_width), int(dec_width), 1])

    def encode(self, z: torch.Tensor, means_cam: torch.Tensor, scales: torch.Tensor,
               rotmats_cam: torch.Tensor) -> torch.Tensor:
        """Phi_proj input [M, D]; scales [M, 2] (see :mod:`splatk.kernels.learned` for the encoding)."""
        rho = torch.linalg.vector_norm(means_cam, dim=1, keepdim=True).clamp_min(1e-12)
        log_rho = torch.log(rho)
        return torch.cat([z, means_cam / rho, log_rho / LOG_DIST_SCALE,
                          (torch.log(scales) - log_rho + LOG_ANGLE_SHIFT) / LOG_ANGLE_SCALE,
                          rotmats_cam.reshape(-1, 9)], 1)

    def project(self, z, means_cam, scales, rotmats_cam) -> torch.Tensor:
        """z_after = Phi_proj(z, mu_cam, s, R_cam): [M, latent2d_dim]."""
        return self.proj(self.encode(z, means_cam, scales, rotmats_cam))

    def logits(self, uv: torch.Tensor, z_after: torch.Tensor) -> torch.Tensor:
        """Phi_dec_planar before the sigmoid. uv [..., 2], z_after [..., L] (broadcast) -> [...]."""
        first, _, mid, _, last = self.dec
        h = F.linear(z_after, first.weight[:, 2:], first.bias) + F.linear(uv, first.weight[:, :2])
        h = F.leaky_relu(h, LEAKY_SLOPE)
        h = F.leaky_relu(mid(h), LEAKY_SLOPE)
        return last(h)[..., 0]

    def exact(self, uv: torch.Tensor, idx: torch.Tensor, z_after: torch.Tensor) -> torch.Tensor:
        """Reference: d at samples uv [P, 2] of primitives idx [P]; 0 outside the unit disk."""
        d = torch.sigmoid(self.logits(uv, z_after[idx]))
        return d * ((uv * uv).sum(-1) <= 1.0)

    def nodes(self) -> torch.Tensor:
        """[G*G, 2] grid nodes (u, v), row-major in v."""
        g = torch.linspace(-1.0, 1.0, self.grid)
        vv, uu = torch.meshgrid(g, g, indexing="ij")
        return torch.stack([uu, vv], -1).reshape(-1, 2)

    def table(self, z_after: torch.Tensor) -> torch.Tensor:
        """[M, G, G] sigmoid(Phi_dec_planar) at the grid nodes (one batched call per view).

        The same function as ``sigmoid(logits(nodes, z_after))``, laid out feature-major: the
        hidden activations are [width, M*G*G] rather than [M*G*G, width]. With width 8 the
        row-major form makes every matrix product a long, 8-wide one that BLAS (and the
        weight gradients, a reduction over M*G*G rows) handle poorly; feature-major they are
        8 long contiguous rows. Measured (7500 surfels, 8x8 grid, one thread, loaded 2-core
        machine, medians of 7): forward + backward 60 -> 44 ms, forward without grad
        18.5 -> 13.6 ms. The first layer splits into a per-primitive
        part (z_after) plus a per-node part (u, v), added by broadcasting.
        """
        first, _, mid, _, last = self.dec
        m, g2 = z_after.shape[0], self.grid * self.grid
        a = F.linear(z_after, first.weight[:, 2:], first.bias)               # [M, C]
        b = first.weight[:, :2] @ self.nodes().to(z_after).T                 # [C, G*G]
        h = (a.T[:, :, None] + b[:, None, :]).reshape(a.shape[1], m * g2)    # [C, M*G*G]
        h = F.leaky_relu(h, LEAKY_SLOPE)
        h = F.leaky_relu(torch.addmm(mid.bias[:, None], mid.weight, h), LEAKY_SLOPE)
        d = torch.sigmoid(torch.addmm(last.bias[:, None], last.weight, h))  # [1, M*G*G]
        return d.reshape(m, self.grid, self.grid)

    def lookup(self, table: torch.Tensor, uv: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Bilinear table lookup at uv [P, 2] of primitives idx [P]; 0 outside the unit disk."""
        return bilinear(table, idx, uv) * ((uv * uv).sum(-1) <= 1.0)


@register_kernel
class SurfelLearnedKernel(PlanarKernel):
    """The learned planar kernel as a planar-model kernel.

    Args:
        grid: table nodes per axis per primitive and view (8; 64 samples of Phi_dec_planar).
        latent_dim, latent2d_dim, proj_width, dec_width: network shapes (10, 10, 64, 8; a weights
            file must match them).
        freeze_iters: networks frozen for this many iterations (as the volumetric learned kernel).
        net_lr, net_lr_final: exponential decay of the networks' LR after the freeze.
        net_lr_mult: multiplies the network LR; None = 10 without pretrained weights, else 1
            (the volumetric kernel's rule, paper Sec. 5.4).
        z_lr: Adam LR of the per-primitive latents (the volumetric z3d default).
        weights: "default" (the shipped file when it exists, else He init), a path from
            `splatk pretrain --kind planar`, or "none" (He init).
    """

    name = "learned"

    @classmethod
    def scale_to_run(cls, options: dict, factor: float, keep=frozenset(), schedules: bool = True,
                     lrs: bool = True) -> dict:
        return scale_learned_options(options, factor, keep, schedules, lrs, "z_lr", 1e-4, 2000)
    needs_view = True

    def __init__(self, grid: int = 8, latent_dim: int = 10, latent2d_dim: int = 10,
                 proj_width: int = 64, dec_width: int = 8, freeze_iters: int = 2000,
                 net_lr: float = 1.6e-4, net_lr_final: float = 1.6e-6,
                 net_lr_mult: float | None = None, z_lr: float = 1e-4,
                 weights: str | None = "default"):
        super().__init__()
        self.net = LearnedPlanarKernel(latent_dim, latent2d_dim, proj_width, dec_width, grid)
        self.freeze_iters = int(freeze_iters)
        self.net_lr, self.net_lr_final = float(net_lr), float(net_lr_final)
        self.z_lr = float(z_lr)
        w = "none" if weights is None else str(weights)
        if w == "default" and not DEFAULT_PLANAR_WEIGHTS.is_file():
            w = "none"  # nothing shipped: He init, recorded as such
        self.weights = w
        if w != "none":
            self.load_pretrained(DEFAULT_PLANAR_WEIGHTS if w == "default" else Path(w).expanduser())
        self.net_lr_mult = float(net_lr_mult) if net_lr_mult is not None else (1.0 if w != "none" else 10.0)
        self._arch = dict(grid=int(grid), latent_dim=int(latent_dim), latent2d_dim=int(latent2d_dim),
                          proj_width=int(proj_width), dec_width=int(dec_width))

    @property
    def options(self) -> dict:
        return {**self._arch, "freeze_iters": self.freeze_iters, "net_lr": self.net_lr,
                "net_lr_final": self.net_lr_final, "net_lr_mult": self.net_lr_mult,
                "z_lr": self.z_lr, "weights": self.weights}

    def load_pretrained(self, path: Path) -> None:
        from ..errors import InputError

        if not path.is_file():
            raise InputError(path, "planar learned-kernel weights file not found",
                             "make it with `splatk pretrain --kind planar` or pass weights: none")
        obj = read_weights_file(path, PLANAR_WEIGHTS_FORMAT, "planar learned-kernel",
                                "splatk pretrain --kind planar")
        try:
            self.net.load_state_dict(obj["state_dict"])
        except RuntimeError as e:
            raise InputError(path, "weights are for another network shape",
                             "pretrain with the same kernel options or pass weights: none") from e

    def init_primitive_params(self, n, device):
        return {"z": torch.zeros(n, self.net.latent_dim, device=device)}  # paper Sec. 4.5

    def learning_rates(self):
        return {"z": self.z_lr}

    def network_learning_rate(self, it: int, progress: float) -> float:
        """0 during the freeze, then net_lr -> net_lr_final exponentially over the remaining
        progress (the schedule of :meth:`splatk.kernels.learned.LearnedKernel.network_learning_rate`)."""
        if it <= self.freeze_iters or self.net_lr <= 0:
            return 0.0
        p0 = progress * self.freeze_iters / max(it, 1)
        q = 1.0 if p0 >= 1.0 else min(1.0, max(0.0, (progress - p0) / (1.0 - p0)))
        lo = max(self.net_lr_final, 1e-30)
        return math.exp((1.0 - q) * math.log(self.net_lr) + q * math.log(lo)) * self.net_lr_mult

    def profile(self, prims, view):
        z_after = self.net.project(prims["z"], view.means_cam, view.scales, view.rotmats_cam)
        return PlanarProfile("grid", self.net.table(z_after))


__all__ = ["LearnedPlanarKernel", "SurfelLearnedKernel", "gaussian_surfel", "SUPPORT_SIGMAS", "_he_init"]
