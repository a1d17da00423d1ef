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

    @classmethod
    def scale_to_run(cls, options: dict, factor: float, keep=frozenset(), schedules: bool = True,
                     lrs: bool = True) -> dict:
        """Changes to this kernel's ``options`` for a run of ``factor`` (< 1) x the 30k
        iterations its defaults are tuned for: step-count schedules (with ``schedules``) and
        learning rates (with ``lrs``). Options given in ``options`` or named in ``keep`` stay.
        Returns {option: new value}; the caller applies them. Default: nothing to scale."""
        return {}

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


#: a learned kernel's latent and network LRs rise by 30k / iters on a short run, at most this much
KERNEL_LR_MULT_MAX = 10.0


def scale_learned_options(options: dict, factor: float, keep, schedules: bool, lrs: bool,
                          latent_key: str, latent_lr: float, freeze_iters: int) -> dict:
    """:meth:`Kernel.scale_to_run` of the learned kernels (volumetric and planar): the networks'
    freeze (paper Sec. 4.5: 2000 of 30k iterations) shrinks in proportion, or a 2000-iteration
    run would leave them frozen throughout; the latents and networks get 30k / iters fewer
    steps, and their LRs decay over the shorter run, so their LRs rise by that factor, at most
    x10 (cup / fox at 1/8, 2000 iterations, k=4: latent and network LR x10 gave +0.97 / +0.39 dB)."""
    given = set(options) | set(keep)
    changes: dict = {}
    if schedules and "freeze_iters" not in given:
        changes["freeze_iters"] = round(freeze_iters * factor)
    if lrs:
        boost = min(KERNEL_LR_MULT_MAX, 1 / factor)
        if latent_key not in given:
            changes[latent_key] = latent_lr * boost
        if "net_lr_mult" not in given:
            pretrained = str(options.get("weights", "default")).lower() != "none"
            # without pretraining the paper's x10 already applies; do not stack the two
            changes["net_lr_mult"] = max(1.0 if pretrained else 10.0, round(boost, 3))
    return changes


KERNELS: dict[str, type[Kernel]] = {}


def register_kernel(cls: type[Kernel]) -> type[Kernel]:
    KERNELS[cls.name] = cls
    return cls
