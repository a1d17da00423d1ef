"""Fixtures for the data loader tests: the shared real scenes and tiny generated scenes."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="package")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="package")
def demo_dir(tmp_path_factory) -> Path:
    """A small demo scene (9 views, 32 px: 7 train / 2 test), generated once; do not modify."""
    from splatk.data.synthetic import make_demo_scene

    return make_demo_scene(tmp_path_factory.mktemp("demo"), num_views=9, size=32)


def write_tiny_colmap(root: Path, model: str = "PINHOLE", n_images: int = 3, size: tuple[int, int] = (40, 30),
                      text: bool = False, n_points: int = 20, nan_pose: int | None = None) -> Path:
    """A tiny COLMAP scene written with pycolmap: ``root/sparse/0`` + ``root/images/*.png``.

    Cameras sit on the -z side of the origin looking along +z at random points around it;
    image number ``nan_pose`` (1-based) gets a NaN translation.
    """
    w, h = size
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    for i in range(1, n_images + 1):
        cam = pycolmap.Camera.create_from_model_id(i, getattr(pycolmap.CameraModelId, model), 50.0, w, h)
        rec.add_camera_with_trivial_rig(cam)
        im = pycolmap.Image(name=f"img_{i:02d}.png", camera_id=i, image_id=i)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.0, 0.0, 1.0])),
                                np.array([np.nan if i == nan_pose else 0.1 * i, 0.0, 4.0]))
        rec.add_image_with_trivial_frame(im, pose)
        img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        (root / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "images" / im.name), img)
    for _ in range(n_points):
        rec.add_point3D(rng.normal(size=3), pycolmap.Track(), rng.integers(0, 255, 3).astype(np.uint8))
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(model_dir))
    return root


@pytest.fixture
def tiny_colmap(tmp_path):
    """Factory: ``tiny_colmap(**kwargs)`` writes a tiny COLMAP scene under tmp_path and returns its root."""
    counter = iter(range(1000))

    def make(**kwargs) -> Path:
        return write_tiny_colmap(tmp_path / f"colmap_{next(counter)}", **kwargs)

    return make
