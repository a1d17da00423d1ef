"""Standard dataset layouts load as their papers use them: Mip-NeRF 360 (images_N/ for
--downscale N, every 8th view for test), NeRF-synthetic (800 px RGBA, its own test split), Tanks
& Temples and Deep Blending as the 3DGS repository ships them (COLMAP sparse/0 + images/ per
scene folder), and nerfstudio's images_N/; COLMAP's fisheye camera models are OpenCV's fisheye
model. Tiny copies are built in tmp_path by layouts.py."""
from __future__ import annotations

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from layouts import colmap_copy, nerfstudio_copy, write_downscaled
from splatk.data import load_scene
from splatk.errors import InputError


@pytest.fixture(scope="module")
def mipnerf360(shared_data, tmp_path_factory):
    """bonsai (a Mip-NeRF 360 scene) with images_2/ and images_4/ beside images/, sizes rounded
    up as the release has them."""
    root = colmap_copy(shared_data / "bonsai", tmp_path_factory.mktemp("m360") / "bonsai")
    for factor in (2, 4):
        write_downscaled(root / "images", factor)
    return root


def test_mipnerf360_downscale_reads_images_n(mipnerf360):
    full = load_scene(mipnerf360, load_images=False)
    scene = load_scene(mipnerf360, downscale=4)
    assert (len(scene.train), len(scene.test)) == (73, 11)  # every 8th of 84 is a test view
    assert [c.name for c in scene.test] == sorted(c.name for c in scene.cameras)[::8]
    for cam, ref in zip(scene.cameras, full.cameras):
        assert cam.image_path.parent.name == "images_4"
        # 800x533 / 4, rounded up, less the undistortion's crop of invalid border pixels
        assert 198 <= cam.width <= 200 and 132 <= cam.height <= 134
        assert tuple(cam.image.shape[1::-1]) == (cam.width, cam.height)
    # bonsai is SIMPLE_RADIAL: the full-size camera scaled by the size ratio of each axis, then
    # undistorted at that size, matches the full-size undistorted camera scaled the same way
    cam, ref = scene.train[0], full.train[0]
    assert cam.fx / ref.fx == pytest.approx(200 / 800, rel=0.01)
    assert cam.fy / ref.fy == pytest.approx(134 / 533, rel=0.01)


def test_mipnerf360_without_images_n_resizes_the_originals(mipnerf360):
    scene = load_scene(mipnerf360, downscale=8, load_images=False)  # there is no images_8/
    assert all(c.image_path.parent.name == "images" for c in scene.cameras)
    assert (scene.train[0].width, scene.train[0].height) == (100, 67)
    # a downscale that is not a whole number never looks for a folder
    assert all(c.image_path.parent.name == "images"
               for c in load_scene(mipnerf360, downscale=2.5, load_images=False).cameras)


def test_images_n_of_the_wrong_size_names_the_folder(shared_data, tmp_path):
    root = colmap_copy(shared_data / "bonsai", tmp_path / "bonsai")
    write_downscaled(root / "images", 2, size=(300, 200))  # not 1/2 of 800x533
    with pytest.raises(InputError) as info:
        load_scene(root, downscale=2, load_images=False)
    assert str(root / "images_2") in str(info.value) and "300x200" in str(info.value)
    assert "regenerate images_2/" in info.value.fix


def test_images_n_missing_an_image_names_the_folder(shared_data, tmp_path):
    root = colmap_copy(shared_data / "bonsai", tmp_path / "bonsai")
    small = write_downscaled(root / "images", 4)
    victim = sorted(small.iterdir())[5]
    victim.unlink()
    with pytest.raises(InputError) as info:
        load_scene(root, downscale=4, load_images=False)
    assert str(small) in str(info.value) and victim.name in str(info.value)


def test_nerf_synthetic_800px_with_its_own_test_split(shared_data, tmp_path):
    """lego's layout (transforms_{train,val,test}.json, RGBA r_N.png listed without extension)
    at the release's 800 px."""
    src, root = shared_data / "lego", tmp_path / "lego"
    for split, count in (("train", 3), ("val", 1), ("test", 2)):
        doc = json.loads((src / f"transforms_{split}.json").read_text())
        doc["frames"] = doc["frames"][:count]
        (root / split).mkdir(parents=True)
        for fr in doc["frames"]:
            img = cv2.imread(str(src / (fr["file_path"] + ".png")), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(root / (fr["file_path"] + ".png")), cv2.resize(img, (800, 800)))
        (root / f"transforms_{split}.json").write_text(json.dumps(doc))
    scene = load_scene(root)
    assert (len(scene.train), len(scene.test)) == (3, 2)
    assert all(c.name.startswith("test/") for c in scene.test)
    cam = scene.train[0]
    angle = json.loads((root / "transforms_train.json").read_text())["camera_angle_x"]
    assert (cam.width, cam.height) == (800, 800) and cam.fx == pytest.approx(400 / math.tan(angle / 2))
    assert scene.background == (1.0, 1.0, 1.0) and cam.alpha is not None
    transparent = cam.alpha.numpy() == 0
    assert transparent.any() and (cam.image.numpy()[transparent] == 255).all()  # composited on white
    half = load_scene(root, downscale=2, load_images=False)
    assert half.train[0].width == 400 and half.train[0].fx == pytest.approx(cam.fx / 2)


@pytest.mark.parametrize("group, name", [("tandt", "train"), ("db", "playroom")])
def test_3dgs_release_scene_folders(shared_data, tmp_path, tiny_colmap, group, name):
    """The 3DGS release's tandt/{train,truck} and db/{playroom,drjohnson}: one COLMAP scene
    (undistorted PINHOLE cameras, sparse/0 + images/) per folder."""
    root = tmp_path / group / name
    if group == "tandt":
        colmap_copy(shared_data / "cup", root)  # a real SIMPLE_PINHOLE model
        n, points = 77, 9262
    else:
        root.parent.mkdir(parents=True)
        tiny_colmap(model="PINHOLE", n_images=17, n_points=40).rename(root)
        n, points = 17, 40
    scene = load_scene(root, load_images=False)
    assert scene.source == "colmap" and scene.points.shape == (points, 3)
    assert (len(scene.train), len(scene.test)) == (n - math.ceil(n / 8), math.ceil(n / 8))
    assert scene.warnings == []


def test_nerfstudio_images_n(shared_data, tmp_path):
    root = nerfstudio_copy(shared_data / "cup", tmp_path / "ns", views=3, downscale=2, fisheye=False, points=0)
    write_downscaled(root / "images", 2)
    full = load_scene(root, test_every=0)
    scene = load_scene(root, downscale=2, test_every=0)
    for cam, ref in zip(scene.train, full.train):
        assert cam.image_path.parent.name == "images_2"
        assert (cam.width, cam.height) == (200, 150) and cam.fx == pytest.approx(ref.fx / 2)
        assert tuple(cam.mask.shape) == (150, 200)  # the full-size mask, resized with its image
        assert cam.mask[:, :40].any().item() is False and cam.mask[:, 60:].all().item() is True
    shutil.rmtree(root / "images_2")
    write_downscaled(root / "images", 2, size=(90, 70))
    with pytest.raises(InputError, match="images_2"):
        load_scene(root, downscale=2, load_images=False)


@pytest.mark.parametrize("model, params", [
    ("SIMPLE_FISHEYE", [50.0, 20.0, 15.0]),
    ("FISHEYE", [50.0, 52.0, 20.0, 15.0]),
    ("SIMPLE_RADIAL_FISHEYE", [50.0, 20.0, 15.0, 0.1]),
    ("RADIAL_FISHEYE", [50.0, 20.0, 15.0, 0.1, -0.02]),
    ("OPENCV_FISHEYE", [50.0, 52.0, 20.0, 15.0, 0.1, 0.02, -0.01, 0.001]),
])
def test_colmap_fisheye_models_are_opencv_fisheye(model, params):
    """Each COLMAP fisheye model projects as the cv2.fisheye camera splatk reads it as."""
    import pycolmap

    from splatk.data.colmap import _intrinsics

    cam = pycolmap.Camera.create_from_model_id(1, getattr(pycolmap.CameraModelId, model), 50.0, 40, 30)
    cam.params = params
    intr = _intrinsics(cam, None)
    assert intr.fisheye and len(intr.dist) == 4
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-0.6, 0.6, (50, 2)), np.ones((50, 1))], axis=1)
    expected = cam.img_from_cam(points)  # COLMAP: pixel centres at +0.5
    K = np.array([[intr.fx, 0.0, intr.cx - 0.5], [0.0, intr.fy, intr.cy - 0.5], [0.0, 0.0, 1.0]])
    got, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                       np.array(intr.dist).reshape(4, 1))
    assert np.allclose(got.reshape(-1, 2) + 0.5, expected, atol=1e-6)
