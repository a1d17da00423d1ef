"""Pre-downscaled image folders, as Mip-NeRF 360 and nerfstudio datasets ship them.

Beside ``images/`` such a scene has ``images_2/``, ``images_4/``, ``images_8/`` holding the same
file names at 1/2, 1/4, 1/8 of the size. ``--downscale N`` (a whole number) reads ``images_N/``
when it exists instead of resizing the originals, as 3DGS's ``--images images_4`` and nerfstudio's
``downscale_factor`` do. The camera (calibrated at full size) is scaled by each axis's actual size
ratio, since these folders round sizes their own way (Mip-NeRF 360's garden: 5187x3361 becomes
1297x841). An image whose size is not within one pixel of 1/N of its original is an error naming
the folder: it was made from other images or at another factor.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from ..errors import InputError
from ._common import View, image_size, resolve_image
from .cameras import at_size


def downscaled_folder(folder: Path, downscale: float) -> Path | None:
    """``<folder>_N`` beside ``folder`` when ``downscale`` is a whole number N >= 2 and that folder
    exists, else None."""
    if downscale < 2 or downscale != int(downscale):
        return None
    candidate = folder.with_name(f"{folder.name}_{int(downscale)}")
    return candidate if candidate.is_dir() else None


def top_folder(path: Path, root: Path) -> Path | None:
    """The folder directly under ``root`` that holds ``path`` (``root/images`` for
    ``root/images/a/b.jpg``), or None for a file directly in ``root`` or outside it."""
    try:
        parts = Path(os.path.normpath(path.relative_to(root))).parts
    except ValueError:
        return None
    return root / parts[0] if len(parts) >= 2 and parts[0] not in (".", "..") else None


def read_downscaled(view: View, folder: Path, small: Path, factor: int) -> View:
    """``view`` read from ``small`` (the ``folder_N`` copy of ``folder``, which holds
    ``view.path``): the same relative name there, the camera scaled to that image's size.

    Raises:
        InputError: naming ``small``, when the image is missing there or not 1/``factor`` of
            the original's size (within a pixel).
    """
    rel = Path(os.path.normpath(view.path)).relative_to(os.path.normpath(folder))
    path = resolve_image(small / rel)
    if path is None:
        raise InputError(small, f"has no {rel.as_posix()} (the 1/{factor} copy of {folder.name}/{rel.as_posix()})",
                         f"add it, or remove {small.name}/ so that splatk resizes {folder.name}/ itself")
    w, h = image_size(path)
    W, H = view.intr.width, view.intr.height
    if abs(w - W / factor) > 1 or abs(h - H / factor) > 1:
        raise InputError(small, f"{rel.as_posix()} is {w}x{h}, but 1/{factor} of its {W}x{H} original is about "
                         f"{W / factor:.0f}x{H / factor:.0f}",
                         f"regenerate {small.name}/ from {folder.name}/ at 1/{factor}, or remove it so that "
                         f"splatk resizes {folder.name}/ itself")
    return replace(view, intr=at_size(view.intr, w, h), path=path)


def use_downscaled(views: list[View], root: Path, downscale: float) -> tuple[list[View], float]:
    """(views, remaining downscale): every view whose image lies in a folder directly under
    ``root`` that has a ``_N`` copy for ``downscale`` = N is read from that copy (and needs no
    further resizing); all views must come from such a copy or none (one scale for the scene)."""
    smalls: dict[Path, Path | None] = {}
    for v in views:
        folder = top_folder(v.path, root)
        if folder is not None and folder not in smalls:
            smalls[folder] = downscaled_folder(folder, downscale)
    if not any(smalls.values()):
        return views, downscale
    missing = [f for f, s in smalls.items() if s is None]
    loose = [v for v in views if top_folder(v.path, root) is None]
    if missing or loose:
        # some images have a 1/N copy and some do not: resizing those would mix two resamplings
        have = next(s for s in smalls.values() if s is not None)
        what = f"{missing[0].name}/ has no {missing[0].name}_{int(downscale)}/" if missing else \
            f"{loose[0].path.name} is not in a folder"
        raise InputError(have, f"is a 1/{int(downscale)} copy of some of the scene's images, but {what}",
                         f"give every image folder its _{int(downscale)} copy, or remove {have.name}/ "
                         "so that splatk resizes the originals")
    out = []
    for v in views:
        folder = top_folder(v.path, root)
        out.append(read_downscaled(v, folder, smalls[folder], int(downscale)))
    return out, 1.0
