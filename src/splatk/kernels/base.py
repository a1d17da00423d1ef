"""What a splatting kernel is: a name, its support, its per-primitive parameters, and how it
turns a view of the primitives into the radial profile the rasteriser composites."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..backends import Backend, Profile


@dataclass
class ViewContext:
    """Camera-space attributes of the primitives visible in one view (paper Eq. 5 inputs).

    All None for kernels with ``needs_view = False`` (render skips computing them).

    Attributes:
        means_cam: [M, 3] camera-space centres.
        scales: [M, 3] activated scales.
        rotmats_cam: [M, 3, 3] primitive rotations in camera space.
        backend: the backend rendering the view; a kernel may take native versions of its
            ops from it (e.g. :meth:`Backend.learned_profile`). None: the kernel's torch code
            (views made outside a render: pretraining, plots, export).
    """

    means_cam: torch.Tensor | None
    scales: torch.Tensor | None
    rotmats_cam: torch.Tensor | None
    backend: Backend | None = None


class Kernel(nn.Module):
    """Base class. Subclasses set ``name`` and ``support_sigmas`` and override the hooks.

    A kernel's ``nn.Module`` parameters are its *global* networks (the learned kernel's
    Phi_proj / Phi_dec); per-primitive parameters live in the model's parameter dict under
    the names returned by :meth:`init_primitive_params`.
    """

    name: str = "base"
    #: support of the profile in units of the projected sigma (bounding ellipse at r = 1)
    support_sigmas: float = 3.0
    #: whether :meth:`profile` reads the :class:`ViewContext` (a backend's projection may skip
    #: computing camera-space centres and rotations for kernels that do not)
    needs_view: bool = False

    def init_primitive_params(self, n: int, device: torch.device) -> dict[str, torch.Tensor]:
        """Raw (pre-activation) per-primitive parameters for ``n`` new primitives."""
        return {}

    def learning_rates(self) -> dict[str, float]:
        """Learning rate of each per-primitive parameter this kernel owns."""
        return {}

    def profile(self, prims: dict[str, torch.Tensor], view: ViewContext) -> Profile:
        """The profile for the visible primitives (``prims`` holds their rows only)."""
        raise NotImplementedError

    def network_learning_rate(self, it: int, progress: float) -> float:
        """LR of the global networks at iteration ``it`` / progress in [0, 1] (0 = frozen)."""
        return 0.0

    def gaussian_scale_factor(self, prims: dict[str, torch.Tensor]) -> torch.Tensor | float:
        """Per-primitive factor f such that a Gaussian of scale ``f * scale`` best matches this
        kernel's footprint ([N] or a float); used to bake kernels into a 3DGS PLY."""
        return 1.0


def read_weights_file(path, fmt: str, what: str, remake: str) -> dict:
    """The dict a `splatk pretrain` weights file holds, checked to be of format ``fmt``; bad files
    raise an InputError naming the file (``what``: the kind of file, ``remake``: the command)."""
    from ..errors import InputError
    from ..torch_files import load_torch_file

    try:
        obj = load_torch_file(path, f"re-run `{remake}`")
    except InputError:
        raise
    except Exception as e:
        raise InputError(path, f"cannot read {what} weights ({type(e).__name__})", f"re-run `{remake}`") from e
    if not isinstance(obj, dict) or obj.get("format") != fmt:
        raise InputError(path, f"not a {what} weights file", f"make one with `{remake}`")
    return obj


KERNELS: dict[str, type[Kernel]] = {}


def register_kernel(cls: type[Kernel]) -> type[Kernel]:
    KERNELS[cls.name] = cls
    return cls
