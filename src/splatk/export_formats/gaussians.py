"""A model as plain 3DGS Gaussians, the only primitive PLY, ``.splat`` and SPZ files hold.

A non-Gaussian kernel is baked to the closest Gaussian (scale times the kernel's
:meth:`~splatk.kernels.Kernel.gaussian_scale_factor`); a colour model other than spherical
harmonics keeps its base colour (the SH DC term). :func:`gaussians_of` says which of these
approximations it made, so the caller can measure and report them.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..colors import make_color_model
from ..functional.sh import num_sh_bases
from ..kernels import make_kernel
from ..models.volumetric import SplatModel


@dataclass(frozen=True)
class Gaussians:
    """N Gaussians in the 3DGS PLY's conventions (raw, pre-activation values), float32 arrays.

    Attributes:
        means: [N, 3] centres.
        log_scales: [N, 3] natural log of the 1-sigma scale along each local axis.
        quats: [N, 4] unit rotation quaternions (w, x, y, z).
        opacity_logits: [N] opacity before the sigmoid.
        sh0: [N, 3] SH DC coefficients (colour = 0.5 + SH_C0 * sh0).
        sh_rest: [N, K, 3] higher SH bands, K = (degree + 1)^2 - 1, coefficient-major.
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh0: np.ndarray
    sh_rest: np.ndarray

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """The same Gaussians with SH bands above ``degree`` dropped."""
        return replace(self, sh_rest=self.sh_rest[:, : num_sh_bases(degree) - 1])

    def to_model(self) -> SplatModel:
        """A Gaussian-kernel, SH-colour model of these Gaussians: what a 3DGS viewer draws,
        as splatk renders it."""
        prims = {"means": self.means, "log_scales": self.log_scales, "quats": self.quats,
                 "opacity_logits": self.opacity_logits, "sh0": self.sh0[:, None, :], "sh_rest": self.sh_rest}
        prims = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in prims.items()}
        return SplatModel(make_kernel("gaussian"), make_color_model("sh", sh_degree=self.sh_degree), prims)


def gaussians_of(model) -> tuple[Gaussians, list[str]]:
    """``model``'s Gaussians and the approximations made to get them (empty for a Gaussian
    model with SH colour), e.g. ``["beta kernel approximated by Gaussians"]``."""
    prims = {k: v.detach().cpu() for k, v in model.prims.items()}
    f_dc, f_rest = model.color.base_rgb_params(prims)
    factor = model.kernel.gaussian_scale_factor(prims)
    if isinstance(factor, torch.Tensor):
        factor = factor.detach().cpu()[:, None]
    log_scales = prims["log_scales"] + torch.log(torch.as_tensor(factor, dtype=torch.float32))
    quats = torch.nn.functional.normalize(prims["quats"], dim=-1)
    as_np = lambda t: np.ascontiguousarray(t.numpy(), dtype=np.float32)  # noqa: E731
    gaussians = Gaussians(as_np(prims["means"]), as_np(log_scales), as_np(quats),
                          as_np(prims["opacity_logits"]), as_np(f_dc), as_np(f_rest))
    changes = []
    if model.kernel.name != "gaussian":
        changes.append(f"{model.kernel.name} kernel approximated by Gaussians")
    if model.color.name != "sh":
        changes.append(f"{model.color.name} colour reduced to its base colour")
    return gaussians, changes
