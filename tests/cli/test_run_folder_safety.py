"""What splatk never does to a user's files (docs/reliability.md): `--overwrite` replaces only
folders splatk wrote, never an input, the current directory or a folder without splatk's marker;
every option is checked before anything is deleted; one writer per folder; outputs never land on
inputs; a resume that would change the run, or a scene that changed, is refused.

Each case runs the real CLI in-process (click's CliRunner) on the 24 px demo scene, torch backend.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from splatk.data.synthetic import make_demo_scene
from splatk.outputs import MARKER, OutputDir
from splatk_cli.main import cli

FAST = ["--backend", "torch", "--threads", "1", "-q"]
TINY = ["--iters", "20", "--budget", "100", *FAST]


def run(*args, env=None):
    return CliRunner().invoke(cli, [str(a) for a in args], env=env)


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes' hash and mtime."""
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(res, *needles: str) -> str:
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("splatk: error: "), res.output
    assert "Traceback" not in res.output
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_demo_scene(tmp_path_factory.mktemp("s") / "scene", num_views=6, size=24)


@pytest.fixture
def old_run(scene, tmp_path) -> Path:
    out = tmp_path / "run"
    res = run("fit", scene, "--out", out, *TINY)
    assert res.exit_code == 0, res.output
    assert (out / MARKER).is_file()
    return out


# ---- --overwrite ------------------------------------------------------------------------------------
def test_overwrite_never_replaces_the_scene_or_a_folder_holding_it(scene, tmp_path):
    before = snapshot(scene)
    one_error_line(run("fit", scene, "--out", scene, "--overwrite", *TINY), "is the input")
    one_error_line(run("fit", scene, "--out", scene.parent, "--overwrite", *TINY), "contains the input")
    assert snapshot(scene) == before


def test_overwrite_never_replaces_the_current_directory(scene, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (work / "notes.txt").write_text("mine")
    monkeypatch.chdir(work)
    one_error_line(run("fit", scene, "--out", ".", "--overwrite", *TINY), "current directory")
    assert (work / "notes.txt").read_text() == "mine"


def test_overwrite_never_replaces_a_folder_splatk_did_not_write(scene, tmp_path):
    mine = tmp_path / "photos"
    mine.mkdir()
    (mine / "holiday.jpg").write_bytes(b"precious")
    one_error_line(run("fit", scene, "--out", mine, "--overwrite", *TINY), "marker")
    assert (mine / "holiday.jpg").read_bytes() == b"precious" and len(list(mine.iterdir())) == 1


def test_overwrite_replaces_a_run_folder(scene, old_run):
    (old_run / "stale.txt").write_text("from the old run")
    res = run("fit", scene, "--out", old_run, "--overwrite", *TINY)
    assert res.exit_code == 0, res.output
    assert not (old_run / "stale.txt").exists() and (old_run / "model.pt").is_file()


def test_overwrite_is_not_read_from_the_environment(scene, old_run):
    before = snapshot(old_run)
    res = run("fit", scene, "--out", old_run, *TINY, env={"SPLATK_FIT_OVERWRITE": "1"})
    one_error_line(res, "not empty", "--resume")  # fit can go on with the run; it says how
    assert snapshot(old_run) == before


@pytest.mark.parametrize("bad", [["--sh-degree", "7"], ["--checkpoint-every", "0"], ["--budget", "0"],
                                 ["--time-budget", "0"], ["--threads", "100000"], ["--downscale", "0.001"],
                                 ["--iters", "-5"], ["--kernel", "learned", "--k", "1"]])
def test_bad_option_with_overwrite_leaves_the_old_run(scene, old_run, bad):
    before = snapshot(old_run)
    one_error_line(run("fit", scene, "--out", old_run, "--overwrite", *TINY, *bad))
    assert snapshot(old_run) == before


def test_budget_beyond_memory_says_what_fits(scene, tmp_path):
    line = one_error_line(run("fit", scene, "--out", tmp_path / "r", *FAST, "--budget", "1e12"), "--budget")
    assert "at most" in line and "primitives fit here" in line
    assert not (tmp_path / "r").exists()


def test_preset_values_are_type_and_range_checked(scene, tmp_path):
    wrong_type = tmp_path / "wrong_type.yaml"
    wrong_type.write_text("iters: lots\n")
    one_error_line(run("fit", scene, "--out", tmp_path / "a", "--preset", wrong_type, *FAST), str(wrong_type))
    out_of_range = tmp_path / "out_of_range.yaml"
    out_of_range.write_text("sh_degree: 9\n")
    one_error_line(run("fit", scene, "--out", tmp_path / "b", "--preset", out_of_range, *FAST),
                   "--sh-degree 9", str(out_of_range))
    not_a_mapping = tmp_path / "list.yaml"
    not_a_mapping.write_text("- 1\n- 2\n")
    one_error_line(run("fit", scene, "--out", tmp_path / "c", "--preset", not_a_mapping, *FAST), str(not_a_mapping))


# ---- one writer per folder -----------------------------------------------------------------------
def test_second_writer_is_refused_naming_the_holder(scene, old_run):
    before = snapshot(old_run)
    with OutputDir(old_run, "fit run", keep=True):  # as a running fit holds it
        line = one_error_line(run("fit", scene, "--out", old_run, "--overwrite", *TINY), "another splatk process")
        assert f"pid {os.getpid()}" in line
        one_error_line(run("fit", "--resume", "--out", old_run, "-q"), "another splatk process")
    after = snapshot(old_run)
    assert {k: v for k, v in after.items() if not k.startswith(".splatk")} == \
        {k: v for k, v in before.items() if not k.startswith(".splatk")}
    res = run("fit", scene, "--out", old_run, "--overwrite", *TINY)  # released: the next writer goes ahead
    assert res.exit_code == 0, res.output


# ---- outputs never overwrite inputs -------------------------------------------------------------------
def test_export_renders_needs_an_empty_or_own_folder(scene, old_run, tmp_path):
    target = tmp_path / "gt"
    target.mkdir()
    (target / "r_0.png").write_bytes(b"ground truth")
    one_error_line(run("export", old_run, "--format", "renders", "--out", target), "not empty")
    one_error_line(run("export", old_run, "--format", "renders", "--out", target, "--overwrite"), "marker")
    assert (target / "r_0.png").read_bytes() == b"ground truth"
    fresh = tmp_path / "renders"
    assert run("export", old_run, "--format", "renders", "--out", fresh, "--backend", "torch").exit_code == 0
    assert "--resume" not in one_error_line(run("export", old_run, "--format", "renders", "--out", fresh), "not empty")
    res = run("export", old_run, "--format", "renders", "--out", fresh, "--backend", "torch", "--overwrite")
    assert res.exit_code == 0, res.output


def test_export_file_is_not_overwritten_without_the_flag(old_run, tmp_path):
    ply = tmp_path / "model.ply"
    ply.write_bytes(b"someone else's")
    one_error_line(run("export", old_run, "--format", "ply", "--out", ply), "exists")
    assert ply.read_bytes() == b"someone else's"
    one_error_line(run("export", old_run, "--format", "native", "--out", old_run / "model.pt", "--overwrite"),
                   "is an input")
    assert run("export", old_run, "--format", "ply", "--out", ply, "--overwrite").exit_code == 0


def test_image_never_writes_into_the_photo_folder(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    photo = photos / "p.png"
    cv2.imwrite(str(photo), (np.random.default_rng(0).random((32, 48, 3)) * 255).astype(np.uint8))
    before = snapshot(photos)
    args = ["image", photo, "--iters", "2", "--no-lpips", "-q", "--kernel", "gaussian", "--budget-bytes", "2KB"]
    one_error_line(run(*args, "--out", photos), "contains the input")
    one_error_line(run(*args, "--out", photos, "--overwrite"), "contains the input")
    assert snapshot(photos) == before
    assert run(*args, "--out", tmp_path / "fit").exit_code == 0
    line = one_error_line(run(*args, "--out", tmp_path / "fit"), "not empty")
    assert "--resume" not in line  # `splatk image` has no --resume to offer
    assert run(*args, "--out", tmp_path / "fit", "--overwrite").exit_code == 0


# ---- honest resume ------------------------------------------------------------------------------------
def test_resume_refuses_a_changed_setting_and_applies_a_changeable_one(scene, old_run):
    one_error_line(run("fit", "--resume", "--out", old_run, "--kernel", "beta", "-q"), "kernel", "gaussian", "beta")
    one_error_line(run("fit", "--resume", "--out", old_run, "--budget", "5000", "-q"), "budget")
    res = run("fit", "--resume", "--out", old_run, "--iters", "30", "-q")
    assert res.exit_code == 0, res.output
    doc = yaml.safe_load((old_run / "config.yaml").read_text())
    assert doc["settings"]["train"]["iters"] == 30
    assert doc["sources"]["iters"].startswith("changed on resume at iteration 20")


def test_resume_prints_the_runs_kernel(scene, tmp_path):
    out = tmp_path / "beta"
    assert run("fit", scene, "--out", out, "--kernel", "beta", *TINY).exit_code == 0
    res = run("fit", "--resume", "--out", out, "--iters", "25")
    assert res.exit_code == 0, res.output
    assert "kernel beta" in res.output.replace("\n", " ")


def test_resume_refuses_another_or_a_changed_scene(scene, old_run, tmp_path):
    other = make_demo_scene(tmp_path / "other", num_views=6, size=24, seed=3)
    one_error_line(run("fit", other, "--resume", "--out", old_run, "-q"), "is not the scene of the run")
    img = next((scene / "train").glob("*.png"))
    original = img.read_bytes()
    try:
        pixels = cv2.imread(str(img), cv2.IMREAD_UNCHANGED)
        pixels[pixels.shape[0] // 2] = 255 - pixels[pixels.shape[0] // 2]  # a row across the object
        if pixels.shape[2] == 4:
            pixels[..., 3] = 255
        cv2.imwrite(str(img), pixels)
        one_error_line(run("fit", "--resume", "--out", old_run, "--iters", "30", "-q"), "the scene changed")
    finally:
        img.write_bytes(original)


def test_test_split_and_background_from_the_command_line(scene, tmp_path):
    out = tmp_path / "r"
    res = run("fit", scene, "--out", out, *TINY, "--test-every", "3", "--background", "black")
    assert res.exit_code == 0, res.output
    settings = yaml.safe_load((out / "config.yaml").read_text())["settings"]
    assert settings["test_every"] == 3 and settings["background"] == [0.0, 0.0, 0.0]
    meta = torch.load(out / "model.pt", weights_only=True)["meta"]
    assert meta["background"] == [0.0, 0.0, 0.0] and meta["test_every"] == 3
    one_error_line(run("fit", scene, "--out", tmp_path / "bad", *TINY, "--test-every", "0"), "--test-every")
