"""Which train views draw each primitive of a view-dependent kernel.

The learned kernel's profile is view-dependent, peak included (decision 0106), so a primitive can
be drawn by one train view and switched off in every other train view that sees it: a floater in
front of one camera that the other cameras' losses never charge for, drawn again by a new view
near it (decision 0113). A Gaussian in that place is drawn by every view that sees it.

A primitive's **effective peak** in a view is its opacity x d(0), the profile's value at its
centre as the kernel computes it for that view; a view **sees** it when its centre is in front of
the camera and its support overlaps the image (the projection's visibility). It is **one-view**
when two or more train views see it, its largest effective peak over them is at least ``FLOOR``,
and its second-largest is under ``RATIO`` x the largest: one view draws it and the others that see
it switch it off. A primitive that one train view alone sees is not counted: that is a floater
any kernel can have, not the learned kernel's own (counting it cost cup in tuning, decision 0113).
"""
from __future__ import annotations

import torch

from ..kernels.base import ViewContext
from ..models.volumetric import SplatModel

#: second-largest over largest effective peak under which one view alone draws a primitive
RATIO = 0.25
#: the largest effective peak a primitive needs to count: fainter ones draw little anywhere
FLOOR = 0.1


@torch.no_grad()
def effective_peaks(model, backend, cameras, index: torch.Tensor | None = None) -> torch.Tensor:
    """[N, V] opacity x d(0) of each primitive in each camera that sees it; NaN where it does not.
    With ``index`` (primitive indices), only those rows: [len(index), V]."""
    prims, scales, opacity = model.prims, model.scales, model.opacities
    if index is not None:
        prims = {k: p.index_select(0, index) for k, p in prims.items()}
        scales, opacity = scales.index_select(0, index), opacity.index_select(0, index)
    peaks = torch.full((opacity.shape[0], len(cameras)), float("nan"), device=opacity.device)
    for v, cam in enumerate(cameras):
        viewmat, K = cam.world_to_cam.to(opacity.device), cam.K.to(opacity.device)
        proj = backend.project(prims["means"], prims["quats"], scales, viewmat, K, cam.width, cam.height,
                               support_sigmas=model.kernel.support_sigmas, want_view=True)
        idx = torch.nonzero(proj.visible).flatten()
        vis = {k: p.index_select(0, idx) for k, p in prims.items()}
        view = ViewContext(proj.means_cam.index_select(0, idx), scales.index_select(0, idx),
                           proj.rotmats_cam.index_select(0, idx), backend)
        centre_value = model.kernel.profile(vis, view).params[:, 0]
        peaks[idx, v] = opacity.index_select(0, idx) * centre_value
    return peaks


def one_view_mask(peaks: torch.Tensor, ratio: float = RATIO, floor: float = FLOOR) -> torch.Tensor:
    """[N] primitives one view draws, from :func:`effective_peaks`' [N, V] table."""
    if peaks.shape[1] < 2:
        return torch.zeros(peaks.shape[0], dtype=torch.bool, device=peaks.device)
    seen_by = (~peaks.isnan()).sum(1)
    top2 = torch.nan_to_num(peaks, nan=0.0).topk(2, dim=1).values
    largest, second = top2[:, 0], top2[:, 1]
    return (seen_by >= 2) & (largest >= floor) & (second < ratio * largest)


def one_view_primitives(model, backend, cameras) -> torch.Tensor:
    """[N] bool: the primitives one of ``cameras`` draws (all False for a kernel whose profile does
    not depend on the view, and for planar primitives, whose profile is a grid)."""
    if not (isinstance(model, SplatModel) and model.kernel.needs_view) or len(cameras) == 0:
        return torch.zeros(model.num_primitives, dtype=torch.bool, device=model.prims["means"].device)
    if backend is None:
        raise ValueError("finding one-view primitives draws the train views: give the ops (backend) that draw them")
    # d(0) is a sigmoid's value, at most 1, so no primitive has an effective peak above its
    # opacity: those under FLOOR can never count. Drawing only the others gives the same mask at a
    # fraction of the cost (about half of a trained model's primitives are under it).
    opacity = model.opacities
    candidates = torch.nonzero(opacity >= FLOOR).flatten()
    mask = torch.zeros(model.num_primitives, dtype=torch.bool, device=opacity.device)
    if candidates.numel() > 0:
        mask[candidates] = one_view_mask(effective_peaks(model, backend, cameras, candidates))
    return mask
