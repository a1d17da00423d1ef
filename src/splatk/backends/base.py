"""What a backend is: the ops one render and one training step need, for one device.

A model's render and the trainer's loss call these and nothing else that depends on the
implementation, so a new backend is one class in one module (see ``docs/design.md``).
:class:`splatk.backends.torch_backend.TorchBackend` is the specification every op is tested
against; a faster backend subclasses it and overrides the ops it has a native version of.
"""
from __future__ import annotations

from typing import Callable, ClassVar

import torch

from ..functional.projection import Projected
from .types import PlanarProfile, Profile, RasterOutput


class Backend:
    """The ops of one implementation on one device; made by :func:`splatk.backends.get`.

    Class attributes:
        name: the registered name (``--backend NAME``).
        priority: ``auto`` takes the available backend with the highest priority.
    """

    name: ClassVar[str] = ""
    priority: ClassVar[int] = 0

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)

    @classmethod
    def unavailable_reason(cls, device: torch.device) -> str | None:
        """Why this backend cannot run on ``device`` here, or None when it can."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.device)!r})"

    # ---- the ops every backend has ------------------------------------------------------
    def project(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                support_sigmas: float = 3.0, want_view: bool = False) -> Projected:
        """EWA projection of ellipsoids (``functional.projection.project_ellipsoids``).

        Args:
            means: [N, 3]; quats: [N, 4] (w, x, y, z); scales: [N, 3] activated.
            viewmat: [4, 4] world->camera; K: [3, 3].
            support_sigmas: the kernel's support; conics are normalised so it is r2 = 1.
            want_view: fill ``means_cam`` [N, 3] and ``rotmats_cam`` [N, 3, 3] (a backend may
                leave them empty otherwise).
        """
        raise NotImplementedError

    def sh_colors(self, sh0: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor,
                  degree: int) -> torch.Tensor:
        """Spherical-harmonics colour: sh0 [N, 1, 3], sh_rest [N, B, 3] (bands above ``degree``
        ignored), dirs [N, 3] -> rgb [N, 3] (``functional.sh.eval_sh``)."""
        raise NotImplementedError

    def rasterize(self, means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                  colors: torch.Tensor, depths: torch.Tensor, profile: Profile, width: int,
                  height: int, background: torch.Tensor) -> RasterOutput:
        """Composite 2D splats (the contract in :mod:`splatk.backends`); background: [C]."""
        raise NotImplementedError

    def rasterize_planar(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                         opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
                         K: torch.Tensor, width: int, height: int, profile: PlanarProfile,
                         background: torch.Tensor | None = None) -> RasterOutput:
        """Composite planar splats (``backends.planar_torch.rasterize_planar`` is the contract)."""
        raise NotImplementedError

    def ssim(self, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """Mean SSIM (``metrics.ssim``, 11x11 window, 'same' padding) of img [H, W, C] against
        the photo ref [H, W, C]; differentiable in ``img``."""
        raise NotImplementedError

    # ---- optional native versions (None: the caller computes it in torch) ---------------
    # The learned kernel's inference ops. A backend without them, or whose versions have no
    # backward while autograd records, returns None and the kernel runs its torch code.
    def learned_encode(self, z3d, means_cam, scales, rotmats_cam, use_mu: bool, use_s: bool,
                       use_R: bool, dist_scale: float, angle_shift: float,
                       angle_scale: float) -> torch.Tensor | None:
        """``LearnedKernel.encode``: [M, D] Phi_proj inputs, or None."""
        return None

    def learned_decode(self, z2d, layers, radii2, slope: float) -> torch.Tensor | None:
        """``LearnedKernel.decode`` with the sigmoid, ``layers`` Phi_dec's three ``nn.Linear``:
        [M, P], or None."""
        return None

    def learned_profile(self, z3d, means_cam, scales, rotmats_cam, use_mu: bool, use_s: bool,
                        use_R: bool, dist_scale: float, angle_shift: float, angle_scale: float,
                        proj_layers, dec_layers, radii2, slope: float) -> torch.Tensor | None:
        """``LearnedKernel.profile`` with Phi_proj in bf16: encode -> Phi_proj -> Phi_dec at
        ``radii2``, [M, P], or None."""
        return None

    #: the sum of 2D image splats (:class:`splatk.image.model.Splats2D`, whose torch path is
    #: the specification): ``(means [N, 2], chol [N, 3], colors [N, 3], extras [N, E], bbox
    #: int32 [N, 4], kind, aux, width, height) -> [H, W, 3]``; None where a backend has no
    #: version of its own (the model's torch path draws; see ``backends.image_cpu``)
    render_image_splats: ClassVar[Callable[..., torch.Tensor] | None] = None
