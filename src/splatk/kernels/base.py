"""What a splatting kernel is: a primitive type and a name, its support, its per-primitive
parameters, and how it turns a view of the primitives into the profile the rasteriser composites.

Kernels are registered by (primitive, name): ``("volumetric", "beta")``, ``("planar", "learned")``.
:func:`make_kernel` builds one, :func:`kernel_names` lists those of a primitive type."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..backends import Backend, Profile
from ..errors import InputError


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
    """Base class. Subclasses set ``name`` and ``support_sigmas`` (and ``primitive`` for another
    primitive type than volumetric) and override the hooks.

    A kernel's ``nn.Module`` parameters are its *global* networks (the learned kernel's
    Phi_proj / Phi_dec); per-primitive parameters live in the model's parameter dict under
    the names returned by :meth:`init_primitive_params`.
    """

    name: str = "base"
    #: the primitive type the kernel draws (a volumetric kernel returns a
    #: :class:`~splatk.backends.Profile`, a planar one a :class:`~splatk.backends.PlanarProfile`)
    primitive: str = "volumetric"
    #: support of the profile in units of the projected sigma (bounding ellipse at r = 1)
    support_sigmas: float = 3.0
    #: the trainer's scale regulariser charges this kernel's scales times this
    #: (see LearnedKernel's ``scale_reg_weight``)
    scale_reg_weight: float = 1.0
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

    def network_groups(self) -> list[tuple[list[torch.nn.Parameter], float]]:
        """The global networks' parameters as (parameters, multiplier of
        :meth:`network_learning_rate`) groups, one Adam group each."""
        params = list(self.parameters())
        return [(params, 1.0)] if params else []

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
    x10 (docs/decisions/0001-short-run-scaling.md)."""
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


#: (primitive, name) -> kernel class
KERNELS: dict[tuple[str, str], type[Kernel]] = {}


def register_kernel(cls: type[Kernel]) -> type[Kernel]:
    """Class decorator: register ``cls`` under ``(cls.primitive, cls.name)``."""
    KERNELS[(cls.primitive, cls.name)] = cls
    return cls


def kernel_names(primitive: str | None = None) -> list[str]:
    """Sorted names of the kernels of ``primitive`` (None: of every primitive type)."""
    return sorted({name for p, name in KERNELS if primitive is None or p == primitive})


def make_kernel(name: str, primitive: str = "volumetric", **options) -> Kernel:
    """The kernel ``name`` of ``primitive`` built with ``options``.

    An unknown volumetric kernel is a ValueError; a kernel with no version for another primitive
    type, or an option that kernel does not take (a volumetric-only one such as ``k``), is an
    InputError saying which kernels that primitive type has.
    """
    cls = KERNELS.get((primitive, name))
    names = kernel_names(primitive)
    if cls is None and primitive == "volumetric":
        raise ValueError(f"unknown kernel {name!r}; choose from {', '.join(names)}")
    if cls is None:
        if not names:
            raise ValueError(f"unknown primitive type {primitive!r}")
        raise InputError(None, f"kernel {name!r} has no {primitive} version",
                         f"with --primitive {primitive} use --kernel {' or '.join(names)}")
    if primitive == "volumetric":
        return cls(**options)
    try:
        return cls(**options)
    except TypeError as e:  # an option of a volumetric kernel (e.g. k)
        raise InputError(None, f"{primitive} kernel {name!r}: {e}",
                         "drop volumetric-only kernel options such as --k") from None
