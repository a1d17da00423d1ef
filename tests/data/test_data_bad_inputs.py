"""Bad input gives an InputError whose one-line message names the offending file (never a traceback
from pycolmap, cv2 or json). Built in tmp_path from tiny generated scenes."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from splatk.data import load_scene
from splatk.errors import InputError


def copy_demo(demo_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(demo_dir, dst)
    return dst


def expect_error(path: Path, names: str | Path, **kwargs) -> InputError:
    """Load ``path`` and check the InputError names ``names`` (a file name or path)."""
    with pytest.raises(InputError) as info:
        load_scene(path, **kwargs)
    err = info.value
    msg = str(err)
    assert "\n" not in msg
    assert Path(names).name in msg, msg
    assert err.fix, msg
    return err


def frames_json(scene: Path) -> tuple[Path, dict]:
    path = scene / "transforms_train.json"
    return path, json.loads(path.read_text())


# ---------------------------------------------------------------------------------------------- folders


def test_missing_folder(tmp_path):
    expect_error(tmp_path / "nope", "nope")


def test_no_recognised_layout(tmp_path):
    (tmp_path / "empty_scene").mkdir()
    err = expect_error(tmp_path / "empty_scene", "empty_scene")
    assert "sparse" in err.problem and "transforms" in err.problem


def test_colmap_without_images_folder(tiny_colmap):
    root = tiny_colmap()
    shutil.rmtree(root / "images")
    expect_error(root, "images")


# ---------------------------------------------------------------------------------------------- images


@pytest.mark.parametrize("fmt", ["colmap", "transforms"])
def test_zero_byte_image(fmt, tiny_colmap, demo_dir, tmp_path):
    root = tiny_colmap() if fmt == "colmap" else copy_demo(demo_dir, tmp_path)
    img = sorted((root / ("images" if fmt == "colmap" else "train")).glob("*.png"))[1]
    img.write_bytes(b"")
    err = expect_error(root, img, load_images=False)  # caught before any decoding
    assert "0 bytes" in err.problem


@pytest.mark.parametrize("fmt", ["colmap", "transforms"])
@pytest.mark.parametrize("load_images", [False, True])
def test_corrupt_image(fmt, load_images, tiny_colmap, demo_dir, tmp_path):
    root = tiny_colmap() if fmt == "colmap" else copy_demo(demo_dir, tmp_path)
    img = sorted((root / ("images" if fmt == "colmap" else "train")).glob("*.png"))[1]
    img.write_bytes(b"this is not a png" * 20)
    err = expect_error(root, img, load_images=load_images)
    assert "decoded" in err.problem


@pytest.mark.parametrize("fmt", ["colmap", "transforms"])
def test_truncated_image(fmt, tiny_colmap, demo_dir, tmp_path):
    """Header intact, pixel data cut off: passes the header check, fails at decoding."""
    root = tiny_colmap() if fmt == "colmap" else copy_demo(demo_dir, tmp_path)
    img = sorted((root / ("images" if fmt == "colmap" else "train")).glob("*.png"))[1]
    data = img.read_bytes()
    img.write_bytes(data[: len(data) // 2])
    load_scene(root, load_images=False)  # cameras only: the header is fine
    err = expect_error(root, img, load_images=True)
    assert "decoded" in err.problem


def test_missing_colmap_image(tiny_colmap):
    root = tiny_colmap()
    (root / "images" / "img_02.png").unlink()
    expect_error(root, "img_02.png", load_images=False)


def test_colmap_image_size_mismatch(tiny_colmap):
    import cv2
    import numpy as np

    root = tiny_colmap(size=(40, 30))
    cv2.imwrite(str(root / "images" / "img_03.png"), np.zeros((60, 80, 3), np.uint8))
    err = expect_error(root, "img_03.png", load_images=False)
    assert "80x60" in err.problem and "40x30" in err.problem


def test_transforms_image_size_mismatch(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, data = frames_json(root)
    data["w"], data["h"] = 64, 48
    path.write_text(json.dumps(data))
    err = expect_error(root, "r_1.png", load_images=False)
    assert "64x48" in err.problem


def test_missing_frame_file(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, data = frames_json(root)
    data["frames"][2]["file_path"] = "./train/does_not_exist"
    path.write_text(json.dumps(data))
    err = expect_error(root, "does_not_exist")
    assert "transforms_train.json" in err.problem


# ---------------------------------------------------------------------------------------------- transforms.json


def test_invalid_json(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, _ = frames_json(root)
    path.write_text(path.read_text()[:-40])  # cut off mid-file
    err = expect_error(root, path)
    assert "JSON" in err.problem and "line" in err.problem


def test_json_without_frames(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    (root / "transforms_test.json").write_text('{"camera_angle_x": 0.7}')
    expect_error(root, "transforms_test.json")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "x"])
def test_non_finite_pose(bad, demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, data = frames_json(root)
    data["frames"][3]["transform_matrix"][1][3] = bad
    path.write_text(json.dumps(data))  # json writes NaN / Infinity, which Python's json reads back
    err = expect_error(root, path, load_images=False)
    assert data["frames"][3]["file_path"] in err.problem


def test_non_rigid_pose(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, data = frames_json(root)
    data["frames"][0]["transform_matrix"][0][0] *= 3.0
    path.write_text(json.dumps(data))
    expect_error(root, path, load_images=False)


def test_no_focal_length(demo_dir, tmp_path):
    root = copy_demo(demo_dir, tmp_path)
    path, data = frames_json(root)
    del data["camera_angle_x"]
    path.write_text(json.dumps(data))
    err = expect_error(root, path, load_images=False)
    assert "fl_x" in err.fix


def test_bad_downscale(demo_dir):
    with pytest.raises(InputError, match="downscale"):
        load_scene(demo_dir, downscale=0)


# ---------------------------------------------------------------------------------------------- COLMAP model files


@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin"])
@pytest.mark.parametrize("damage", ["truncate", "empty", "garbage", "trailing"])
def test_damaged_model_file(fname, damage, tiny_colmap):
    root = tiny_colmap()
    f = root / "sparse" / "0" / fname
    data = f.read_bytes()
    if damage == "truncate":
        f.write_bytes(data[: len(data) * 2 // 3])
    elif damage == "empty":
        f.write_bytes(b"")
    elif damage == "garbage":
        f.write_bytes(bytes(range(256)) * 4)
    else:
        f.write_bytes(data + b"\x01\x02\x03")
    expect_error(root, fname, load_images=False)


def test_truncated_real_images_bin(shared_data, tmp_path):
    """A real model (beer_can) with images.bin cut in half: pycolmap alone says only
    'Rig with ID ... does not exist'."""
    src = shared_data / "beer_can" / "sparse" / "0"
    if not src.is_dir():
        pytest.skip("beer_can not present")
    root = tmp_path / "beer_can"
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").symlink_to(shared_data / "beer_can" / "images")
    for f in src.iterdir():
        data = f.read_bytes()
        (root / "sparse" / "0" / f.name).write_bytes(data[: len(data) // 2] if f.name == "images.bin" else data)
    err = expect_error(root, "images.bin", load_images=False)
    assert "truncated" in err.problem


def test_colmap_nan_pose(tiny_colmap):
    root = tiny_colmap(nan_pose=2)
    err = expect_error(root, "images.bin", load_images=False)
    assert "img_02.png" in err.problem and "non-finite" in err.problem


def test_missing_model_file(tiny_colmap):
    root = tiny_colmap()
    (root / "sparse" / "0" / "points3D.bin").unlink()
    expect_error(root, "points3D.bin", load_images=False)


@pytest.mark.parametrize("model", ["FOV", "THIN_PRISM_FISHEYE", "EQUIRECTANGULAR"])
@pytest.mark.parametrize("text", [False, True])
def test_unsupported_camera_model(model, text, tiny_colmap):
    root = tiny_colmap(model=model, text=text)
    err = expect_error(root, "cameras.txt" if text else "cameras.bin", load_images=False)
    assert model in err.problem
    assert "SIMPLE_RADIAL" in err.fix and "OPENCV" in err.fix  # lists the supported ones


def test_corrupt_cameras_txt(tiny_colmap):
    root = tiny_colmap(text=True)
    f = root / "sparse" / "0" / "cameras.txt"
    f.write_text(f.read_text().replace(" 40 30 ", " 40 "))
    expect_error(root, "cameras.txt", load_images=False)


# ---------------------------------------------------------------------------------------------- allowed input


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                                   "SIMPLE_FISHEYE", "FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE",
                                   "OPENCV_FISHEYE"])
def test_supported_models_load(model, tiny_colmap):
    sc = load_scene(tiny_colmap(model=model, n_images=3))
    assert len(sc.cameras) == 3 and sc.cameras[0].image.shape == (30, 40, 3)
    assert sc.source == "colmap" and sc.background == (0.0, 0.0, 0.0)


def test_text_model_and_sparse_without_0(tiny_colmap):
    root = tiny_colmap(text=True, n_images=9)
    (root / "sparse" / "0").rename(root / "sparse_tmp")
    (root / "sparse").rmdir()
    (root / "sparse_tmp").rename(root / "sparse")
    sc = load_scene(root, load_images=False)
    assert (len(sc.train), len(sc.test)) == (7, 2) and sc.points.shape == (20, 3)


def test_empty_point_cloud_is_allowed(tiny_colmap):
    sc = load_scene(tiny_colmap(n_points=0), load_images=False)
    assert sc.points.shape == (0, 3) and sc.point_colors.shape == (0, 3)
