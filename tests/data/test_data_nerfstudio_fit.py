"""A nerfstudio-format scene trains with what its files say: the fisheye cameras undistorted, the
masks in the loss and the metrics, the PLY as the initial points; `fit` prints the warning about
unused fields once; `--eval-split` and `--background random` reach the run."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from layouts import nerfstudio_copy
from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.stages.evaluate import run_eval
from splatk.stages.fit import run_fit
from splatk.stages.fit_config import fit_config_from_options
from splatk_cli.main import cli

FAST = {"iters": 3, "budget": 1000, "backend": "torch", "threads": 1}
CLI_FAST = ["--iters", "3", "--budget", "200", "--backend", "torch", "--threads", "1", "-q"]


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def fit(scene, out, **options):
    cfg, _ = fit_config_from_options({**FAST, **options})
    seen = {}

    def on_start(info):
        seen["scene"] = info["scene"]
        seen["means"] = info["model"].prims["means"].detach().clone()

    result = run_fit(scene, out, cfg, on_start=on_start)
    return result, seen


def test_fisheye_masks_and_point_cloud_are_all_used(shared_data, tmp_path):
    root = nerfstudio_copy(shared_data / "cup", tmp_path / "ns", views=4, downscale=8, points=300)
    doc = json.loads((root / "transforms.json").read_text())
    result, seen = fit(root, tmp_path / "run")
    scene = seen["scene"]
    # the PLY's points are the initial primitives, in order
    assert torch.equal(seen["means"], load_scene(root, load_images=False).points)
    assert seen["means"].shape == (300, 3)
    assert yaml.safe_load((result.path / "config.yaml").read_text())["settings"]["train"]["init"] == "sfm"
    # the fisheye cameras came out as pinholes of another focal length (cv2.fisheye, balance 0)
    cam = scene.train[0]
    assert cam.fx != pytest.approx(doc["fl_x"], rel=0.02) and (cam.width, cam.height) == (doc["w"], doc["h"])
    # every view carries its mask into the trainer
    assert all(c.mask is not None and not bool(c.mask[:, :2].any()) for c in scene.cameras)
    assert result.summary["iterations"] == 3


def test_eval_ignores_masked_pixels(shared_data, tmp_path):
    root = nerfstudio_copy(shared_data / "cup", tmp_path / "ns", views=4, downscale=8, fisheye=False, points=100)
    result, seen = fit(root, tmp_path / "run")
    test_view = seen["scene"].test[0]
    before = run_eval(result.path)
    assert before["num_views"] == 1
    # scribble over the masked left quarter of the test image on disk
    img = cv2.imread(str(test_view.image_path))
    img[:, : img.shape[1] // 4] = np.random.default_rng(0).integers(0, 256, img[:, : img.shape[1] // 4].shape)
    cv2.imwrite(str(test_view.image_path), img)
    after = run_eval(result.path)
    for name in ("psnr", "ssim"):
        assert after["mean"][name] == pytest.approx(before["mean"][name], abs=1e-9), name
    # without the mask the scribble counts
    doc = json.loads((root / "transforms.json").read_text())
    for fr in doc["frames"]:
        del fr["mask_path"]
    (root / "transforms.json").write_text(json.dumps(doc))
    assert run_eval(result.path)["mean"]["psnr"] < before["mean"]["psnr"] - 1


def test_fit_prints_unused_fields_once(shared_data, tmp_path):
    root = nerfstudio_copy(shared_data / "cup", tmp_path / "ns", views=4, downscale=8, points=0,
                           extra={"depth_unit_scale_factor": 0.001})
    res = run("fit", root, "--out", tmp_path / "run", *CLI_FAST)
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.output.splitlines() if "warning:" in ln]
    assert len(lines) == 1 and "depth_unit_scale_factor" in lines[0], res.output
    summary = json.loads((tmp_path / "run" / "fit.json").read_text())
    assert len(summary["scene_warnings"]) == 1 and "depth_unit_scale_factor" in summary["scene_warnings"][0]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("demo") / "scene", num_views=6, size=24)


def test_eval_split_none_and_all(demo, tmp_path):
    res = run("fit", demo, "--out", tmp_path / "none", *CLI_FAST, "--eval-split", "none")
    assert res.exit_code == 0, res.output
    assert yaml.safe_load((tmp_path / "none" / "config.yaml").read_text())["settings"]["eval_split"] == "none"
    res = run("eval", tmp_path / "none")
    assert res.exit_code == 2 and "--split train" in res.output and "Traceback" not in res.output
    res = run("eval", tmp_path / "none", "--split", "train", "--json")
    assert res.exit_code == 0 and '"num_views": 6' in res.output, res.output
    assert json.loads((tmp_path / "none" / "metrics_train.json").read_text())["split"] == "train"
    assert not (tmp_path / "none" / "metrics.json").exists()  # the train split has its own file
    res = run("fit", demo, "--out", tmp_path / "all", *CLI_FAST, "--eval-split", "all")
    assert res.exit_code == 0, res.output
    assert run_eval(tmp_path / "all")["num_views"] == 6  # every view, train ones included
    run_eval(tmp_path / "all", split="train")
    assert json.loads((tmp_path / "all" / "metrics.json").read_text())["split"] == "test"  # kept
    res = run("fit", demo, "--out", tmp_path / "bad", *CLI_FAST, "--eval-split", "some")
    assert res.exit_code == 2


def test_background_random_reaches_the_run(demo, tmp_path):
    res = run("fit", demo, "--out", tmp_path / "r", *CLI_FAST, "--background", "random")
    assert res.exit_code == 0, res.output
    settings = yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())["settings"]
    assert settings["train"]["random_background"] is True and settings["background"] is None
    meta = torch.load(tmp_path / "r" / "model.pt", weights_only=True)["meta"]
    assert meta["background"] == [1.0, 1.0, 1.0]  # evaluation uses the scene's own (transforms: white)
