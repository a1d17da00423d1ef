"""nerfstudio datasets: OPENCV_FISHEYE undistorted with cv2.fisheye, mask_path (masked pixels leave
the loss and the metrics), ply_file_path as the initial points, and a warning naming the fields
splatk does not use. Built in tmp_path from the shared cup scene (COLMAP) by layouts.py."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from layouts import cv_K, nerfstudio_copy
from splatk.data import load_scene
from splatk.errors import InputError


def psnr_u8(a: np.ndarray, b: np.ndarray) -> float:
    mse = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean() / 255.0**2
    return -10 * math.log10(max(mse, 1e-12))


@pytest.fixture(scope="module")
def cup(shared_data):
    return shared_data / "cup"


def interior_psnrs(scene, pinhole_views, margin: int = 12) -> list[float]:
    """PSNR of each loaded (undistorted) view against its pinhole original resampled to the
    loaded camera's intrinsics (same pose, so a homography), away from the border."""
    out = []
    for cam, src in zip(scene.train, pinhole_views):
        H = cv_K(src.fx, src.fy, src.cx, src.cy) @ np.linalg.inv(cv_K(cam.fx, cam.fy, cam.cx, cam.cy))
        expected = cv2.warpPerspective(src.image.numpy(), H, (cam.width, cam.height),
                                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        out.append(psnr_u8(cam.image.numpy()[margin:-margin, margin:-margin],
                           expected[margin:-margin, margin:-margin]))
    return out


def test_opencv_fisheye_is_undistorted_with_the_fisheye_model(cup, tmp_path):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=3, downscale=2, masks=False, points=0)
    originals = load_scene(cup, downscale=2, test_every=0).train[:3]
    scene = load_scene(root, test_every=0)
    assert scene.warnings == []
    good = interior_psnrs(scene, originals)
    assert min(good) > 30, good
    # the same file read as OPENCV's perspective model (what splatk did before it knew the field)
    doc = json.loads((root / "transforms.json").read_text())
    doc["camera_model"] = "OPENCV"
    (root / "transforms.json").write_text(json.dumps(doc))
    bad = interior_psnrs(load_scene(root, test_every=0), originals)
    assert max(bad) < 30 and min(good) - max(bad) > 10, (good, bad)


def test_masks_follow_their_image_through_undistortion_and_downscaling(cup, tmp_path):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=2, downscale=4, points=0)
    for downscale in (1, 2):
        scene = load_scene(root, downscale=downscale, test_every=0)
        for cam in scene.train:
            assert cam.mask is not None and cam.mask.dtype == torch.bool
            assert tuple(cam.mask.shape) == (cam.height, cam.width)
            kept = cam.mask.float().mean(0)  # per column
            # the left quarter of the fisheye frame is masked; after undistortion it is still
            # the left part, a bit wider (balance 0 crops to the centre)
            assert kept[:2].max() == 0 and kept[-2:].min() == 1
            assert 0.15 < 1 - float(cam.mask.float().mean()) < 0.5


def test_ply_file_path_gives_the_scene_points(cup, tmp_path):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=2, downscale=4, points=250)
    full = load_scene(cup, load_images=False)
    scene = load_scene(root, load_images=False)
    assert torch.allclose(scene.points, full.points[:250], atol=1e-6)  # the PLY holds float32
    assert torch.allclose(scene.point_colors, full.point_colors[:250], atol=0.5 / 255)


def test_fields_splatk_does_not_use_are_named_in_one_warning(cup, tmp_path):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=3, downscale=4, points=0,
                           extra={"depth_unit_scale_factor": 0.001, "aabb_scale": 16})
    path = root / "transforms.json"
    doc = json.loads(path.read_text())
    for i, fr in enumerate(doc["frames"]):
        fr["depth_file_path"] = f"depths/{i}.png"
        fr["sharpness"] = 10.0  # instant-ngp's blur score: ignored without a word
    path.write_text(json.dumps(doc))
    scene = load_scene(root, load_images=False)
    assert len(scene.warnings) == 1, scene.warnings
    w = scene.warnings[0]
    assert str(path) in w and "depth_unit_scale_factor" in w and "frames[].depth_file_path" in w
    assert "aabb_scale" not in w and "sharpness" not in w


def test_real_instant_ngp_scenes_do_not_warn(shared_data):
    for name in ("fox", "kangaroo", "lego"):
        assert load_scene(shared_data / name, load_images=False).warnings == [], name


@pytest.mark.parametrize("field, value, names", [
    ("camera_model", "EQUIRECTANGULAR", "transforms.json"),
    ("camera_model", ["OPENCV"], "transforms.json"),
    ("ply_file_path", "missing.ply", "missing.ply"),
    ("ply_file_path", "../outside.ply", "transforms.json"),
    ("ply_file_path", "images", "images"),
    ("p1", 0.01, "transforms.json"),  # OPENCV_FISHEYE has no tangential terms
])
def test_bad_nerfstudio_fields_are_errors(cup, tmp_path, field, value, names):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=2, downscale=4, masks=False, points=0,
                           extra={field: value})
    with pytest.raises(InputError) as info:
        load_scene(root, load_images=False)
    assert names in str(info.value) and info.value.fix and "\n" not in str(info.value)


def test_a_corrupt_ply_or_a_missing_mask_names_the_file(cup, tmp_path):
    root = nerfstudio_copy(cup, tmp_path / "ns", views=2, downscale=4, points=50)
    (root / "sparse_pc.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(InputError, match="sparse_pc.ply"):
        load_scene(root, load_images=False)
    (root / "sparse_pc.ply").unlink()
    doc = json.loads((root / "transforms.json").read_text())
    del doc["ply_file_path"]
    (root / "transforms.json").write_text(json.dumps(doc))
    mask = root / doc["frames"][1]["mask_path"]
    mask.unlink()
    with pytest.raises(InputError, match=mask.name):
        load_scene(root, load_images=False)
    cv2.imwrite(str(mask), np.zeros((7, 9), np.uint8))
    with pytest.raises(InputError, match="mask is 9x7"):
        load_scene(root, load_images=False)


@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0, 0.0), (0.08, 0.02, -0.01, 0.002), (-0.05, 0.01, 0.0, 0.0),
                               (0.3, 0.1, 0.0, 0.0)])
def test_fisheye_undistortion_draws_every_pixel_from_inside_the_photo(k):
    """balance = 0: the pinhole's focal length leaves no pixel without a source (no smeared border)."""
    from splatk.data.cameras import Undistorter, fisheye_intrinsics

    intr = fisheye_intrinsics(320, 240, 200.0, 200.0, 160.0, 120.0, k)
    und = Undistorter()
    out, roi = und.geometry(intr)
    assert roi == (0, 0, 320, 240) and (out.width, out.height) == (320, 240)
    # every border pixel of the pinhole image, sent through the fisheye lens (cv2.fisheye.distortPoints
    # of its normalised coordinates), lands inside the fisheye photo
    border = [(x, y) for x in range(320) for y in (0, 239)] + [(x, y) for y in range(240) for x in (0, 319)]
    pts = np.array(border, np.float64) + 0.5  # pixel centres
    normalised = np.stack([(pts[:, 0] - out.cx) / out.fx, (pts[:, 1] - out.cy) / out.fy], -1)
    src = cv2.fisheye.distortPoints(normalised.reshape(-1, 1, 2), cv_K(200.0, 200.0, 160.0, 120.0),
                                    np.array(k).reshape(4, 1)).reshape(-1, 2) + 0.5
    assert src[:, 0].min() >= 0 and src[:, 0].max() <= 320 and src[:, 1].min() >= 0 and src[:, 1].max() <= 240
