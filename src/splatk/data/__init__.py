"""Scenes on disk -> cameras, images, points.

``load_scene`` detects the layout: ``sparse/0`` or ``sparse/`` (COLMAP, read with pycolmap: also
Mip-NeRF 360, Tanks & Temples and Deep Blending as 3DGS ships them) or ``transforms*.json``
(instant-ngp / nerfstudio / NeRF-synthetic). Every camera comes out as an undistorted OpenCV
pinhole; bad input raises :class:`splatk.errors.InputError` naming the file, and what a loader
reads past without using is in ``Scene.warnings``.
"""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .colmap import SUPPORTED_MODELS, find_model_dir, load_colmap
from .transforms import find_transforms, load_transforms
from .types import Camera, Scene

__all__ = ["Camera", "Scene", "SUPPORTED_MODELS", "EVAL_SPLITS", "detect_format", "load_colmap", "load_scene",
           "load_transforms", "scene_summary"]

#: which views a scene holds out: ``held-out`` (the dataset's test list, else every
#: ``test_every``-th view), ``all`` (every view trains and is evaluated, as nerfstudio's
#: ``eval_mode all``), ``none`` (every view trains; no test views)
EVAL_SPLITS = ("held-out", "all", "none")


def detect_format(path: str | Path) -> str:
    """``"colmap"`` or ``"transforms"`` for a scene folder (or a transforms JSON file).

    A folder with both a COLMAP model and a transforms file counts as COLMAP (it has points).
    """
    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        return "transforms"
    if not path.exists():
        raise InputError(path, "scene folder does not exist", "check the path")
    if not path.is_dir():
        raise InputError(path, "is not a scene folder", "pass a folder with sparse/0 or transforms.json")
    if find_model_dir(path) is not None:
        return "colmap"
    if find_transforms(path):
        return "transforms"
    raise InputError(path, "no recognised scene layout (looked for sparse/0/cameras.bin, sparse/cameras.bin, "
                     "transforms.json, transforms_train.json)",
                     "pass a COLMAP scene (sparse/0 + images/) or an instant-ngp / NeRF-synthetic folder")


def load_scene(path: str | Path, downscale: float = 1.0, test_every: int = 8,
               background: tuple[float, float, float] | None = None, load_images: bool = True,
               eval_split: str = "held-out") -> Scene:
    """Load a scene folder in any supported layout.

    Args:
        path: scene folder (or a transforms JSON file).
        downscale: resize images by 1 / downscale and scale the intrinsics.
        test_every: every n-th image (name order) is a test view, unless the dataset has its own
            test list (``transforms_test.json``); 0 = no test views.
        background: RGB in [0, 1] for RGBA compositing and rendering; default white (1, 1, 1) for
            transforms scenes (NeRF-synthetic convention), black (0, 0, 0) for COLMAP scenes.
        load_images: decode images (False: cameras only, e.g. for listing or export).
        eval_split: ``held-out``, ``all`` or ``none`` (:data:`EVAL_SPLITS`).
    """
    if eval_split not in EVAL_SPLITS:
        raise InputError(None, f"eval split {eval_split!r} is not one of {', '.join(EVAL_SPLITS)}",
                         "use --eval-split held-out, all or none")
    fmt = detect_format(path)
    if background is not None:
        background = tuple(float(b) for b in background)
        if len(background) != 3:
            raise InputError(None, f"background must have 3 values (RGB in [0, 1]), got {background}",
                             "e.g. 1,1,1 for white")
    if fmt == "colmap":
        scene = load_colmap(path, downscale=downscale, test_every=test_every, load_images=load_images,
                            background=background or (0.0, 0.0, 0.0))
    else:
        scene = load_transforms(path, downscale=downscale, test_every=test_every,
                                background=background or (1.0, 1.0, 1.0), load_images=load_images)
    if eval_split != "held-out":
        views = sorted(scene.train + scene.test, key=lambda c: c.name)
        scene.train, scene.test = views, (list(views) if eval_split == "all" else [])
    return scene


def scene_summary(scene: Scene) -> dict:
    """Counts, resolution, points and source of a scene, JSON-serialisable, for printing."""
    sizes = sorted({(c.width, c.height) for c in scene.cameras})
    res = [f"{w}x{h}" for w, h in sizes]
    return {
        "root": str(scene.root),
        "source": scene.source,
        "train": len(scene.train),
        "test": len(scene.test),
        "resolution": res[0] if len(res) == 1 else res,
        "points": int(scene.points.shape[0]),
        "background": list(scene.background),
        "images_loaded": all(c.image is not None for c in scene.cameras),
        "masks": sum(c.mask is not None for c in scene.cameras),
        "warnings": list(scene.warnings),
    }
