"""What every 3D primitive model shares: a parameter dict of per-primitive rows, a kernel (whose
``nn.Module`` parameters are the global networks) and a colour model. The volumetric
(:class:`splatk.models.volumetric.SplatModel`) and planar (:class:`splatk.models.planar.PlanarModel`)
models differ in their scales, initialisation and rasteriser only."""
from __future__ import annotations

import torch
from torch import nn

from ..colors import ColorModel


class PrimitiveModel(nn.Module):
    """Per-primitive tensors (first dim N) in ``self.prims``: means [N, 3], log_scales [N, S],
    quats [N, 4] (w, x, y, z), opacity_logits [N], plus the colour model's and the kernel's."""

    def __init__(self, kernel: nn.Module, color: ColorModel, prims: dict[str, torch.Tensor]):
        super().__init__()
        self.kernel = kernel
        self.color = color
        self.prims = nn.ParameterDict({k: nn.Parameter(v.contiguous()) for k, v in prims.items()})

    @property
    def num_primitives(self) -> int:
        return self.prims["means"].shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.prims["log_scales"])

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.prims["opacity_logits"])

    def floats_per_primitive(self) -> int:
        return sum(int(v[0].numel()) for v in self.prims.values())

    def footprint_bytes(self) -> int:
        """float32 bytes of everything stored: per-primitive parameters and global networks."""
        per_prim = 4 * self.floats_per_primitive() * self.num_primitives
        nets = 4 * sum(p.numel() for p in self.kernel.parameters())
        return per_prim + nets

    def learning_rates(self) -> dict[str, float]:
        lrs = {"log_scales": 0.005, "quats": 0.001, "opacity_logits": 0.05}  # 3DGS-MCMC
        lrs.update(self.color.learning_rates())
        lrs.update(self.kernel.learning_rates())
        return lrs
