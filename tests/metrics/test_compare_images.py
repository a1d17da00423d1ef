"""compare_images on PNG files written here, and its input errors."""
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatk.errors import InputError
from splatk.metrics import lpips_available, ssim
from splatk.stages.compare import compare_images, read_rgb

CALIB = Path(__file__).resolve().parents[3] / "shared" / "data" / "lpips_calib"


@pytest.fixture()
def pair(tmp_path):
    rng = np.random.default_rng(0)
    ref = rng.integers(60, 190, (40, 56, 3), dtype=np.uint8)
    signs = rng.integers(0, 2, ref.shape) * 2 - 1
    img = (ref.astype(int) + 10 * signs).astype(np.uint8)  # |error| = 10/255 everywhere
    a, b = tmp_path / "render.png", tmp_path / "gt.png"
    cv2.imwrite(str(a), img[:, :, ::-1])
    cv2.imwrite(str(b), ref[:, :, ::-1])
    return a, b, img, ref


def test_metrics_of_written_pngs(pair):
    a, b, img, ref = pair
    out = compare_images(a, b)
    assert out["psnr"] == pytest.approx(20 * math.log10(25.5), abs=1e-4)
    want_ssim = ssim(torch.from_numpy(img / 255.0), torch.from_numpy(ref / 255.0)).item()
    assert out["ssim"] == pytest.approx(want_ssim, abs=1e-5)
    assert out["size"] == [56, 40] and out["lpips_net"] == "alex"
    if lpips_available("alex"):
        assert 0 < out["lpips"] < 1 and "warnings" not in out
    else:
        assert out["lpips"] is None and out["warnings"]
    only = compare_images(a, b, metrics=("psnr",))
    assert set(only) == {"psnr", "identical", "lpips_net", "background", "size"} and only["identical"] is False


def test_reads_rgb_order_alpha_and_16bit(tmp_path):
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 200  # red
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb[:, :, ::-1])
    bgra = np.concatenate([rgb[:, :, ::-1], np.zeros((4, 5, 1), np.uint8)], axis=2)  # alpha 0
    cv2.imwrite(str(tmp_path / "rgba.png"), bgra)
    cv2.imwrite(str(tmp_path / "grey16.png"), np.full((4, 5), 65535, np.uint16))
    got = read_rgb(tmp_path / "rgb.png")
    assert got.shape == (4, 5, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got[0, 0], [200 / 255, 0, 0])
    # alpha 0: the background shows, white unless told (as scene loading composites it)
    np.testing.assert_array_equal(read_rgb(tmp_path / "rgba.png"), np.ones((4, 5, 3), np.float32))
    np.testing.assert_array_equal(read_rgb(tmp_path / "rgba.png", (0.0, 0.0, 0.0)), np.zeros((4, 5, 3), np.float32))
    np.testing.assert_allclose(read_rgb(tmp_path / "grey16.png"), 1.0)


def test_missing_file(pair, tmp_path):
    a, _, _, _ = pair
    with pytest.raises(InputError, match="not found") as e:
        compare_images(a, tmp_path / "nope.png")
    assert e.value.path == tmp_path / "nope.png"


def test_corrupt_file(pair, tmp_path):
    a, _, _, _ = pair
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(InputError, match="cannot be decoded") as e:
        compare_images(bad, a)
    assert e.value.path == bad


def test_size_mismatch(pair, tmp_path):
    a, _, img, _ = pair
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), img[:30, :50])
    with pytest.raises(InputError, match="50x30 differs") as e:
        compare_images(a, small)
    assert e.value.fix


@pytest.mark.shared_data
@pytest.mark.skipif(not (CALIB / "expected.json").is_file(), reason="no shared/data/lpips_calib")
def test_calibration_pair_psnr_and_lpips():
    want = json.loads((CALIB / "expected.json").read_text())
    out = compare_images(CALIB / "I04_dist.png", CALIB / "I04_ref.png")
    assert out["size"] == [512, 384]
    assert out["psnr"] == pytest.approx(want["psnr_official_rgb8"]["I04"], abs=0.01)
    if out["lpips"] is not None:
        assert out["lpips"] == pytest.approx(want["lpips_alex_official"]["I04"], abs=1e-3)
