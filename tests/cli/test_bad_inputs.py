"""Bad input through the real CLI: exit code 2, one line `splatk: error: <file>: <problem> (<fix>)`,
no traceback, and nothing overwritten - a run folder given as --out keeps every file's bytes and
mtime, even with --overwrite, when the inputs are rejected.

Scenes are built in tmp_path: the demo scene (NeRF-synthetic layout, 32 px) and tiny COLMAP
models written with pycolmap. Most cases run in-process through click's CliRunner; two go
through a real `splatk` process.
"""
from __future__ import annotations

import errno
import json
import os
import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch
import yaml
from click.testing import CliRunner

from splatk.outputs import write_marker
from splatk.stages.fit import RUN_KIND
from splatk_cli.main import cli

ERROR_LINE = re.compile(r"^splatk: error: (?P<where>\S.*?): (?P<problem>.+) \((?P<fix>[^()]*(\([^()]*\)[^()]*)*)\)$")
FAST = ["--backend", "torch", "-q"]  # no native build, no progress bar


# ---------------------------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def demo_src(tmp_path_factory) -> Path:
    from splatk.data.synthetic import make_demo_scene

    return make_demo_scene(tmp_path_factory.mktemp("demo_src"), num_views=6, size=32)


@pytest.fixture
def demo(demo_src, tmp_path) -> Path:
    """A private copy of the demo scene (5 train views, 1 test view, no SfM points)."""
    return Path(shutil.copytree(demo_src, tmp_path / "demo"))


def tiny_colmap(root: Path, model: str = "PINHOLE", n_images: int = 3, n_points: int = 20,
                nan_pose: int | None = None, size=(40, 30)) -> Path:
    """``root/sparse/0`` (binary) + ``root/images/img_XX.png``: cameras on -z looking at points
    around the origin; image ``nan_pose`` (1-based) gets a NaN translation."""
    w, h = size
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    (root / "images").mkdir(parents=True)
    for i in range(1, n_images + 1):
        cam = pycolmap.Camera.create_from_model_id(i, getattr(pycolmap.CameraModelId, model), 50.0, w, h)
        rec.add_camera_with_trivial_rig(cam)
        im = pycolmap.Image(name=f"img_{i:02d}.png", camera_id=i, image_id=i)
        t = np.array([np.nan if i == nan_pose else 0.1 * i, 0.0, 4.0])
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0, 0, 1])), t))
        cv2.imwrite(str(root / "images" / im.name), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    for _ in range(n_points):
        rec.add_point3D(rng.normal(size=3), pycolmap.Track(), rng.integers(0, 255, 3).astype(np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse" / "0"))
    return root


@pytest.fixture
def colmap(tmp_path) -> Path:
    return tiny_colmap(tmp_path / "colmap")


@pytest.fixture
def old_run(tmp_path) -> Path:
    """A previous run folder that a rejected command must leave exactly as it was."""
    run = tmp_path / "old_run"
    (run / "checkpoints").mkdir(parents=True)
    write_marker(run, RUN_KIND)  # splatk wrote it, so --overwrite may replace it once the inputs check out
    (run / "config.yaml").write_text("scene: somewhere\n")
    (run / "model.pt").write_bytes(b"previous model" * 100)
    (run / "checkpoints" / "last.pt").write_bytes(b"previous checkpoint" * 100)
    os.utime(run / "model.pt", ns=(1_600_000_000_000_000_000,) * 2)  # an mtime a rewrite would change
    return run


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def expect_error(args: list[str], names: str | Path, fix: str | None = None, started: bool = False) -> re.Match:
    """Run ``splatk ARGS`` in-process; check exit code 2 and a single well-formed error line that
    names ``names`` (a path or file name) and, if given, contains ``fix`` in the fix part.

    The error line must be all the output, unless ``started`` (training began: fit's one-line
    scene summary may come first)."""
    res = CliRunner().invoke(cli, [str(a) for a in args])
    out = res.output
    detail = f"exit {res.exit_code}, output:\n{out}\nexception: {res.exception!r}"
    assert res.exit_code == 2, detail
    assert "Traceback" not in out, detail
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert [ln for ln in lines if ln.startswith("splatk: error:")] == lines[-1:], detail
    if not started:
        assert len(lines) == 1, detail
    m = ERROR_LINE.match(lines[-1])
    assert m, f"not `splatk: error: <file>: <problem> (<fix>)`: {lines[-1]}"
    assert str(names) in lines[-1] or Path(names).name in m["where"], detail
    if fix is not None:
        assert fix in m["fix"], detail
    return m


def fit(scene, out, *extra) -> list[str]:
    return ["fit", scene, "--out", out, *FAST, *extra]


# ---------------------------------------------------------------------------------------------- scene folders


def test_missing_scene_folder(tmp_path, old_run):
    before = snapshot(old_run)
    expect_error(fit(tmp_path / "no_such_scene", old_run, "--overwrite"), "no_such_scene", "check the path")
    assert snapshot(old_run) == before


def test_folder_that_is_no_scene(tmp_path):
    (tmp_path / "photos").mkdir()
    m = expect_error(fit(tmp_path / "photos", tmp_path / "run"), "photos")
    assert "sparse" in m["problem"] and "transforms" in m["problem"]
    assert not (tmp_path / "run").exists()  # nothing created for a rejected scene


# ---------------------------------------------------------------------------------------------- images


@pytest.mark.parametrize("damage", ["missing", "zero-byte", "corrupt"])
@pytest.mark.parametrize("fmt", ["transforms", "colmap"])
def test_bad_image(fmt, damage, demo, colmap, old_run):
    root = demo if fmt == "transforms" else colmap
    img = root / ("train/r_2.png" if fmt == "transforms" else "images/img_02.png")
    if damage == "missing":
        img.unlink()
    elif damage == "zero-byte":
        img.write_bytes(b"")
    else:
        img.write_bytes(b"\x89PNG\r\n\x1a\n" + b"definitely not pixels" * 30)
    before = snapshot(old_run)
    # the demo's transforms list frames without a suffix (NeRF-synthetic): a missing one is named so
    m = expect_error(fit(root, old_run, "--overwrite"), img.stem if damage == "missing" else img.name)
    assert {"missing": "does not exist", "zero-byte": "0 bytes", "corrupt": "decoded"}[damage] in m["problem"]
    assert snapshot(old_run) == before


def test_image_size_does_not_match_camera(colmap, tmp_path):
    cv2.imwrite(str(colmap / "images" / "img_03.png"), np.zeros((60, 80, 3), np.uint8))
    m = expect_error(fit(colmap, tmp_path / "run"), "img_03.png")
    assert "80x60" in m["problem"] and "40x30" in m["problem"] and "cameras.bin" in m["problem"]


def test_transforms_frame_that_does_not_exist(demo, tmp_path):
    path = demo / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"][1]["file_path"] = "./train/never_rendered"
    path.write_text(json.dumps(data))
    m = expect_error(fit(demo, tmp_path / "run"), "never_rendered", "transforms_train.json")
    assert "does not exist" in m["problem"]


# ---------------------------------------------------------------------------------------------- COLMAP model files


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin"])
def test_damaged_model_file(fname, damage, colmap, old_run):
    f = colmap / "sparse" / "0" / fname
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2] if damage == "truncated" else bytes(range(256)) * 3)
    before = snapshot(old_run)
    m = expect_error(fit(colmap, old_run, "--overwrite"), fname, "re-")
    assert "truncated or corrupt" in m["problem"]
    assert snapshot(old_run) == before


def test_unsupported_camera_model(tmp_path):
    root = tiny_colmap(tmp_path / "fisheye", model="THIN_PRISM_FISHEYE")
    m = expect_error(fit(root, tmp_path / "run"), "cameras.bin", "SIMPLE_RADIAL")
    assert "THIN_PRISM_FISHEYE" in m["problem"]


def test_unknown_camera_model_id(colmap, tmp_path):
    f = colmap / "sparse" / "0" / "cameras.bin"
    data = bytearray(f.read_bytes())
    struct.pack_into("<i", data, 8 + 4, 999)  # first record: camera_id (int32), model_id (int32)
    f.write_bytes(bytes(data))
    m = expect_error(fit(colmap, tmp_path / "run"), "cameras.bin", "SIMPLE_RADIAL")
    assert "999" in m["problem"]


@pytest.mark.parametrize("fmt", ["colmap", "transforms"])
def test_nan_pose(fmt, demo, tmp_path):
    if fmt == "colmap":
        root, names = tiny_colmap(tmp_path / "nan", nan_pose=2), "images.bin"
    else:
        root, names = demo, "transforms_train.json"
        data = json.loads((demo / names).read_text())
        data["frames"][0]["transform_matrix"][0][3] = float("nan")
        (demo / names).write_text(json.dumps(data))
    m = expect_error(fit(root, tmp_path / "run"), names)
    assert "NaN" in m["problem"] or "non-finite" in m["problem"]


@pytest.mark.parametrize("fmt", ["colmap", "transforms"])
def test_empty_point_cloud_with_sfm_init(fmt, demo, tmp_path):
    root = tiny_colmap(tmp_path / "nopts", n_points=0) if fmt == "colmap" else demo
    expect_error(fit(root, tmp_path / "run", "--init", "sfm"), root.name, "--init random")
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------------------------- output folder


def test_existing_output_is_refused_without_overwrite(demo, old_run):
    before = snapshot(old_run)
    expect_error(fit(demo, old_run, "--init", "random"), old_run, "--overwrite")
    assert snapshot(old_run) == before


def _unwritable_dirs(tmp_path) -> list[Path]:
    cases = []
    blocked = tmp_path / "read_only"
    blocked.mkdir()
    blocked.chmod(0o555)
    try:  # root (CI containers) writes through chmod: then this case says nothing
        (blocked / "probe").write_bytes(b"")
        (blocked / "probe").unlink()
    except OSError:
        cases.append(blocked / "run")
    if Path("/proc/self").is_dir():
        cases.append(Path("/proc/splatk_test_run"))
    return cases


def test_unwritable_output(demo, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    outs = [a_file / "run", a_file] + _unwritable_dirs(tmp_path)
    for out in outs:
        m = expect_error(fit(demo, out, "--init", "random"), out, "--out")
        assert "write" in m["problem"] or "not a folder" in m["problem"] or "file" in m["problem"]
    assert a_file.read_text() == "not a folder"


def test_disk_full_while_checkpointing(demo, tmp_path, monkeypatch):
    """ENOSPC in the middle of the second checkpoint write: a clear message, exit 2, and the first
    checkpoint is still the complete last.pt (atomic temp file + os.replace), no temp file left."""
    real_save = torch.save
    calls = {"n": 0}

    def save(obj, f, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            f.write(b"PK\x03\x04 half a checkpoint")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
    run = tmp_path / "run"
    m = expect_error(fit(demo, run, "--init", "random", "--budget", "100", "--iters", "30",
                         "--checkpoint-every", "10", "--sh-degree", "0"), "last.pt", "--resume", started=True)
    assert os.strerror(errno.ENOSPC) in m["problem"]
    assert "iteration 10" in m["fix"] and "free disk space" in m["fix"]
    monkeypatch.setattr(torch, "save", real_save)
    state = torch.load(run / "checkpoints" / "last.pt", weights_only=False)
    assert state["trainer"]["it"] == 10
    assert not list((run / "checkpoints").glob("*.tmp"))
    assert not (run / "model.pt").exists()


# ---------------------------------------------------------------------------------------------- other commands


def test_a_device_this_machine_lacks(demo, old_run, tmp_path):
    """fit, eval and image refuse a missing device in one line, before any work."""
    bad = f"cuda:{torch.cuda.device_count()}"  # one past the last GPU, or CUDA absent altogether
    expect_error(fit(demo, tmp_path / "run", "--device", bad), "--device", "--device cpu")
    assert not (tmp_path / "run" / "checkpoints").exists()
    expect_error(["eval", old_run, "--device", bad], "--device", "--device cpu")
    photo = next(demo.rglob("*.png"))
    expect_error(["image", photo, "--out", tmp_path / "img", "--device", "gpu0", "-q"], "--device", "cuda")
    expect_error(["image", photo, "--out", tmp_path / "img", "--device", "meta", "--backend", "cpu", "-q"],
                 "--device", "--backend torch")


def test_eval_and_export_of_a_missing_run(tmp_path):
    expect_error(["eval", tmp_path / "nope", "--backend", "torch"], "model.pt", "splatk fit")
    expect_error(["export", tmp_path / "nope", "--format", "ply", "--out", tmp_path / "m.ply"], "model.pt")
    assert not (tmp_path / "m.ply").exists()


def test_preset_that_does_not_exist(demo, tmp_path):
    """A --preset that is neither a file nor a shipped preset: one line naming it and the presets
    there are (fit and bench read presets alike)."""
    m = expect_error(fit(demo, tmp_path / "run", "--preset", "no_such_preset"), "no_such_preset", "fast")
    assert "default" in m["fix"] and "bench_quick" in m["fix"]
    expect_error(["bench", demo, "--out", tmp_path / "bench", "--preset", tmp_path / "gone.yaml", "-q"],
                 "gone.yaml", "bench_quick")
    assert not (tmp_path / "run").exists() and not (tmp_path / "bench").exists()


@pytest.mark.parametrize("flags, named, fix", [
    (["--kernel", "beta", "--k", "4"], "--k 4", "--kernel learned"),
    (["--primitive", "planar", "--kernel", "learned", "--k", "4"], "--k 4", "--primitive volumetric"),
    (["--kernel-weights", "w.pt"], "--kernel-weights", "--kernel learned"),
    (["--color", "sb", "--sh-degree", "1"], "--sh-degree 1", "--color sh"),
    (["--test-every", "3", "--eval-split", "all"], "--test-every 3", "--eval-split held-out"),
])
def test_flag_the_chosen_model_has_no_use_for(flags, named, fix, demo, tmp_path):
    """A flag typed for another kernel or colour model is one error line, not silently dropped
    (`--kernel beta --k 4` trained Beta and said nothing); nothing is written."""
    expect_error(fit(demo, tmp_path / "run", *flags), named, fix)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flags, problem, fix", [
    (["--downscale", "0"], "--downscale 0: out of range", "give a number from 1 to"),
    (["--iters", "0"], "--iters 0: out of range", "give a whole number from 1 to"),
])
def test_number_out_of_its_range_names_the_range_once(flags, problem, fix, demo, tmp_path):
    """A number out of range is shown as typed (`0`, not click's `0.0`), the problem says what is
    wrong and the fix gives the range, instead of the range twice."""
    m = expect_error(fit(demo, tmp_path / "run", *flags), flags[0], fix)
    assert m.string.startswith(f"splatk: error: {problem} ("), m.string
    assert m["fix"].count(" from ") == 1 and m.string.count(" from ") == 1, m.string
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flags, named, fix", [
    (["--kernel", "gaussian", "--grid", "4"], "--grid", "--kernel learned"),
    (["--kernel", "gabor", "--exact"], "--exact", "--kernel learned"),
    (["--mode", "paper", "--shapes", "8"], "--shapes", "--mode tuned"),
])
def test_image_flag_the_chosen_kernel_has_no_use_for(flags, named, fix, demo, tmp_path):
    """`splatk image` alike: a learned-kernel flag with another kernel, or one paper mode fixes, is
    one error line and nothing is written."""
    photo = next(demo.rglob("*.png"))
    expect_error(["image", photo, "--out", tmp_path / "img", "--iters", "2", "-q", *flags], named, fix)
    assert not (tmp_path / "img").exists()


def test_test_every_on_a_scene_with_its_own_test_list_is_a_warning(demo, tmp_path):
    """The demo scene lists its test views (transforms_test.json): a typed --test-every cannot
    change them, so fit says so in one warning line and trains (a script over a whole dataset
    passes one --test-every to every scene)."""
    res = CliRunner().invoke(cli, [str(a) for a in fit(demo, tmp_path / "run", "--test-every", "3", "--iters", "2")])
    assert res.exit_code == 0, res.output
    warned = [ln for ln in res.output.splitlines() if ln.startswith("warning: --test-every 3")]
    assert len(warned) == 1 and "transforms_test.json" in warned[0], res.output
    quiet = CliRunner().invoke(cli, [str(a) for a in fit(demo, tmp_path / "run2", "--iters", "2")])
    assert quiet.exit_code == 0 and "--test-every" not in quiet.output, quiet.output


def test_preset_may_set_options_of_a_kernel_the_command_line_replaces(demo, tmp_path):
    """A preset's k stays allowed when the command line picks another kernel: presets set options
    for the kernels they pick, and the command line beats them."""
    preset = tmp_path / "learned.yaml"
    preset.write_text("kernel: learned\nk: 4\n")
    res = CliRunner().invoke(cli, [str(a) for a in fit(demo, tmp_path / "run", "--preset", preset,
                                                       "--kernel", "gaussian", "--iters", "5")])
    assert res.exit_code == 0, res.output
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["settings"]["kernel"] == "gaussian"


@pytest.mark.parametrize("damage", ["yaml", "not_utf8"])
def test_damaged_yaml_files(damage, demo, tmp_path):
    """A preset, a bench file and a run's config.yaml that cannot be read: one line naming the file,
    and for a YAML error the line and column where the parser stopped (PyYAML's own message spans
    several lines, quoting the input)."""
    text = b"iters: 100\nkernel: [gaussian\n" if damage == "yaml" else b"iters: \xff\n"
    where = "line 3, column 1" if damage == "yaml" else "UTF-8"
    preset = tmp_path / "preset.yaml"
    preset.write_bytes(text)
    m = expect_error(fit(demo, tmp_path / "run", "--preset", preset), preset, "preset")
    assert where in m["problem"] + m["fix"]
    m = expect_error(["bench", demo, "--out", tmp_path / "bench", "--preset", preset, "-q"], preset, "bench file")
    assert where in m["problem"] + m["fix"]
    run = tmp_path / "old"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"checkpoint")
    (run / "config.yaml").write_bytes(text)
    m = expect_error(["fit", "--resume", "--out", run, "-q"], run / "config.yaml", "without --resume")
    if damage == "yaml":
        assert where in m["problem"]
    assert (run / "config.yaml").read_bytes() == text


# ---------------------------------------------------------------------------------------------- real processes


@pytest.mark.parametrize("case", ["corrupt_image", "existing_output"])
def test_real_process(case, demo, old_run):
    """The installed entry point behaves as the in-process runs do (exit status, one line on stderr)."""
    if case == "corrupt_image":
        (demo / "train" / "r_3.png").write_bytes(b"junk" * 50)
        args, name = [str(demo), "--out", str(old_run), "--overwrite"], "r_3.png"
    else:
        args, name = [str(demo), "--out", str(old_run), "--init", "random"], old_run.name
    before = snapshot(old_run)
    exe = shutil.which("splatk")
    cmd = [exe] if exe else [sys.executable, "-m", "splatk_cli.main"]
    proc = subprocess.run(cmd + ["fit", *args, *FAST], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and ERROR_LINE.match(lines[0]) and name in lines[0], proc.stderr
    assert snapshot(old_run) == before
