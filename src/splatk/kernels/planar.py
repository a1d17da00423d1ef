"""Kernels of planar (surfel) primitives, registered by name: what a :class:`PlanarModel` asks of
them is a :class:`~splatk.backends.PlanarProfile` for the visible splats of a view.

* ``gaussian``: the Gaussian surfel exp(-4.5 (u^2 + v^2)) over the 3-sigma disk (2DGS).
* ``learned``: :class:`~splatk.kernels.learned_planar.LearnedPlanarKernel` (Phi_proj +
  Phi_dec_planar, paper Sec. 4.4): per-primitive latent ``z`` [N, 10], sampled per view on a
  G x G grid of (u, v) nodes that the rasteriser interpolates bilinearly (profile ``grid``).

Volumetric-only kernels (beta, student_t) have no planar version; :func:`make_planar_kernel`
says so by name.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import nn

from ..backends import PlanarProfile
from .base import ViewContext, read_weights_file, scale_learned_options
from .learned_planar import LearnedPlanarKernel

#: weights made by ``splatk pretrain --kind planar --steps 10000 --out src/splatk/assets/learned_planar.pt``
#: (Gaussian-surfel target; mean abs error 0.015, see learned_planar.json; 1500 steps gave 0.09)
DEFAULT_PLANAR_WEIGHTS = Path(__file__).resolve().parent.parent / "assets" / "learned_planar.pt"
PLANAR_WEIGHTS_FORMAT = "splatk-learned-planar-kernel"  # stages.pretrain_planar.WEIGHTS_FORMAT


class PlanarKernel(nn.Module):
    """Base class; the hooks mirror :class:`splatk.kernels.base.Kernel` (global networks are the
    module's parameters, per-primitive ones live in the model's parameter dict)."""

    name = "base"
    #: (u, v) support in sigmas; both planar kernels end at the 3-sigma disk
    support_sigmas = 3.0
    needs_view = False

    @property
    def options(self) -> dict:
        return {}

    def init_primitive_params(self, n: int, device: torch.device) -> dict[str, torch.Tensor]:
        return {}

    def learning_rates(self) -> dict[str, float]:
        return {}

    def network_learning_rate(self, it: int, progress: float) -> float:
        return 0.0

    def profile(self, prims: dict[str, torch.Tensor], view: ViewContext) -> PlanarProfile:
        raise NotImplementedError

    @classmethod
    def scale_to_run(cls, options: dict, factor: float, keep=frozenset(), schedules: bool = True,
                     lrs: bool = True) -> dict:
        """As :meth:`splatk.kernels.base.Kernel.scale_to_run`: nothing to scale by default."""
        return {}


class SurfelGaussianKernel(PlanarKernel):
    """The Gaussian surfel (no parameters)."""

    name = "gaussian"

    def profile(self, prims, view):
        return PlanarProfile("gaussian_surfel")


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
    needs_view = True

    @classmethod
    def scale_to_run(cls, options: dict, factor: float, keep=frozenset(), schedules: bool = True,
                     lrs: bool = True) -> dict:
        return scale_learned_options(options, factor, keep, schedules, lrs, "z_lr", 1e-4, 2000)

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


PLANAR_KERNELS: dict[str, type[PlanarKernel]] = {
    SurfelGaussianKernel.name: SurfelGaussianKernel,
    SurfelLearnedKernel.name: SurfelLearnedKernel,
}


def make_planar_kernel(name: str, **options) -> PlanarKernel:
    from ..errors import InputError

    if name not in PLANAR_KERNELS:
        raise InputError(None, f"kernel {name!r} has no planar version",
                         f"with --primitive planar use --kernel {' or '.join(sorted(PLANAR_KERNELS))}")
    try:
        return PLANAR_KERNELS[name](**options)
    except TypeError as e:  # an option of a volumetric kernel (e.g. k)
        raise InputError(None, f"planar kernel {name!r}: {e}",
                         "drop volumetric-only kernel options such as --k") from None
