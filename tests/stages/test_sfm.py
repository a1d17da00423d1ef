"""`splatk sfm`: unposed photos -> a COLMAP scene `splatk fit` accepts.

The real run uses ../shared/data/sacre_coeur_unposed (10 Flickr photos, 10 different cameras,
long side 800) and is skipped without it; about 25 s on 2 cores. The input checks run on
generated images.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk.data import load_scene
from splatk.errors import InputError
from splatk.stages.sfm import run_sfm
from splatk_cli.main import cli

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
SACRE_COEUR = SHARED_DATA / "sacre_coeur_unposed" / "images"


def invoke(*args):
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == 0, f"{res.output}\n{res.exception!r}"
    return res


@pytest.fixture(scope="module")
def sacre_coeur_scene(tmp_path_factory) -> Path:
    if not SACRE_COEUR.is_dir():
        pytest.skip(f"shared test data not found at {SACRE_COEUR}")
    out = tmp_path_factory.mktemp("sfm") / "scene"
    # one thread: COLMAP is seeded, but its multi-threaded matching and mapping are not
    # deterministic, and the number of triangulated points varied 73-950 between runs
    invoke("sfm", SACRE_COEUR, "--out", out, "--threads", "1", "-q")
    return out


@pytest.mark.shared_data
def test_sfm_on_sacre_coeur(sacre_coeur_scene):
    summary = json.loads((sacre_coeur_scene / "sfm.json").read_text())
    scene = load_scene(sacre_coeur_scene)
    assert len(scene.cameras) == summary["registered"] >= 5
    assert scene.points.shape[0] == summary["points"] > 100
    assert summary["mean_reprojection_error_px"] < 2.0
    names = sorted(p.name for p in (sacre_coeur_scene / "images").iterdir())
    assert names == sorted(c.name for c in scene.cameras)  # only registered images, undistorted
    assert (sacre_coeur_scene / "sparse" / "0" / "cameras.bin").is_file()
    assert not list(sacre_coeur_scene.parent.glob(".scene.sfm-*"))  # work folder removed
    # it fits and evaluates (tiny: 1/16 size, a few iterations; the point is that it runs)
    run = sacre_coeur_scene.parent / "run"
    n = torch.get_num_threads()
    invoke("fit", sacre_coeur_scene, "--out", run, "--downscale", "16", "--iters", "10", "--budget", "1000",
           "--backend", "torch", "-q")
    torch.set_num_threads(n)
    res = invoke("eval", run, "--json", "--backend", "torch", "--metrics", "psnr")
    assert math.isfinite(json.loads(res.stdout)["mean"]["psnr"])


def _photos(folder: Path, n: int, seed: int = 0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(folder / f"photo_{i}.jpg"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    return folder


@pytest.mark.parametrize("case", ["missing", "empty", "two", "zero-byte"])
def test_bad_image_folder(case, tmp_path):
    folder = tmp_path / "photos"
    if case == "empty":
        folder.mkdir()
        (folder / "notes.txt").write_text("no photos here")
    elif case == "two":
        _photos(folder, 2)
    elif case == "zero-byte":
        _photos(folder, 4)
        (folder / "photo_2.jpg").write_bytes(b"")
    with pytest.raises(InputError) as info:
        run_sfm(folder, tmp_path / "scene")
    err = info.value
    expected = {"missing": "does not exist", "empty": "no images", "two": "only 2 image(s)",
                "zero-byte": "0 bytes"}[case]
    assert expected in err.problem and err.fix
    assert (err.path.name == "photo_2.jpg") if case == "zero-byte" else (err.path == folder)
    assert not (tmp_path / "scene").exists()


def test_unrelated_images_fail_cleanly(tmp_path):
    """Noise photos share no features: no reconstruction, a message with the counts, no output."""
    folder = _photos(tmp_path / "noise", 3)
    with pytest.raises(InputError) as info:
        run_sfm(folder, tmp_path / "scene")
    msg = info.value.message()
    assert "SfM" in msg and "3" in msg and info.value.fix
    assert ("no reconstruction" in msg) or ("registered only" in msg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]  # no scene, no work folder left


def test_output_checks(tmp_path):
    folder = _photos(tmp_path / "photos", 3)
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        run_sfm(folder, scene)
    with pytest.raises(InputError, match="input photos"):
        run_sfm(folder, tmp_path, overwrite=True)  # would delete the photos
    with pytest.raises(InputError, match="camera model"):
        run_sfm(folder, tmp_path / "other", camera_model="NOT_A_MODEL")
    assert (scene / "keep.txt").read_text() == "mine"
    res = CliRunner().invoke(cli, ["sfm", str(folder), "--out", str(scene), "-q"])
    assert res.exit_code == 2 and res.output.startswith(f"splatk: error: {scene}: output folder exists")
