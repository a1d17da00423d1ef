"""`splatk compare` reads an RGBA pair as `splatk fit` / `splatk eval` do (alpha composited onto the
scene's background), and its --json output is strict JSON even for identical images."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk.data import load_scene
from splatk.metrics import compute_metrics
from splatk_cli.main import cli


def strict_json(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def rgba_pair(tmp_path_factory) -> tuple[Path, Path, Path, Path]:
    """(scene, its test view's RGBA file, a second scene whose test view is an edited RGBA copy,
    that copy). The copy differs where it is opaque and, more, in the colour stored under its
    transparent pixels, which only an alpha-dropping reader sees."""
    from splatk.data.synthetic import make_demo_scene

    root = tmp_path_factory.mktemp("compare_rgba")
    scene = make_demo_scene(root / "scene", num_views=3, size=32)
    ref = next((scene / "test").glob("*.png"))
    bgra = cv2.imread(str(ref), cv2.IMREAD_UNCHANGED)
    assert bgra.shape[2] == 4 and 0 < (bgra[..., 3] == 0).sum() < bgra[..., 3].size  # a real RGBA view
    rng = np.random.default_rng(0)
    edited = bgra.astype(np.int16)
    edited[..., :3] += rng.integers(-12, 13, edited[..., :3].shape, dtype=np.int16)
    edited[bgra[..., 3] == 0, :3] = rng.integers(0, 256, ((bgra[..., 3] == 0).sum(), 3))
    other = Path(shutil.copytree(scene, root / "other"))
    img = other / "test" / ref.name
    cv2.imwrite(str(img), np.clip(edited, 0, 255).astype(np.uint8))
    return scene, ref, other, img


@pytest.mark.parametrize("background", [None, (0.0, 0.0, 0.0)])
def test_rgba_pair_scores_as_the_loader_and_metrics_score_it(rgba_pair, background):
    scene, ref, other, img = rgba_pair
    cams = [load_scene(s, background=background).test for s in (scene, other)]
    (gt,), (test,) = cams
    assert gt.name == test.name
    want = compute_metrics(test.image_float(), gt.image_float(), metrics=("psnr",))["psnr"]
    args = ["compare", str(img), str(ref), "--metrics", "psnr", "--json"]
    if background is not None:
        args += ["--background", ",".join(str(v) for v in background)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    got = strict_json(res.stdout)["psnr"]
    # equal up to scene loading's rounding of the composite to 8 bits (far below the several
    # dB that dropping the alpha channel costs)
    assert got == pytest.approx(want, abs=0.01), (got, want)
    dropped = compute_metrics(torch.from_numpy(cv2.imread(str(img))[..., ::-1] / 255.0).float(),
                              torch.from_numpy(cv2.imread(str(ref))[..., ::-1] / 255.0).float(),
                              metrics=("psnr",))["psnr"]
    assert abs(dropped - want) > 1.0  # the pair tells the two readings apart


def test_identical_images_give_strict_json(rgba_pair):
    _, ref, _, _ = rgba_pair
    res = CliRunner().invoke(cli, ["compare", str(ref), str(ref), "--metrics", "psnr,ssim", "--json"])
    assert res.exit_code == 0, res.output
    out = strict_json(res.stdout)
    assert out["psnr"] is None and out["identical"] is True and out["ssim"] == pytest.approx(1.0)
    assert out["background"] == [1.0, 1.0, 1.0]
    text = CliRunner().invoke(cli, ["compare", str(ref), str(ref), "--metrics", "psnr"])
    assert text.exit_code == 0 and text.stdout.strip() == "psnr: inf"


def test_different_images_are_not_identical(rgba_pair):
    _, ref, _, img = rgba_pair
    res = CliRunner().invoke(cli, ["compare", str(img), str(ref), "--metrics", "psnr", "--json"])
    out = strict_json(res.stdout)
    assert out["identical"] is False and out["psnr"] > 0


@pytest.mark.parametrize("value", ["1,1", "a,b,c", "0,0,2"])
def test_bad_background_is_a_usage_error(rgba_pair, value):
    _, ref, _, _ = rgba_pair
    res = CliRunner().invoke(cli, ["compare", str(ref), str(ref), "--background", value])
    assert res.exit_code == 2 and "--background" in res.output and "Traceback" not in res.output
