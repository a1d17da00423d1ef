"""`splatk render RUN --path ... --out video.mp4`: an H.264 MP4 that OpenCV reads back with the
frames and size asked for, drawn as `eval` draws the views; refuses to overwrite."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk import backends
from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.models.io import load_model
from splatk.stages.fit import FitConfig, run_fit
from splatk.train.trainer import TrainConfig
from splatk_cli.main import cli


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("render_video")
    scene = make_demo_scene(tmp / "scene", num_views=16, size=32)
    cfg = FitConfig(sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=60, budget=300, init="random", backend="torch"))
    return run_fit(scene, tmp / "run", cfg).path


def render(*args):
    return CliRunner().invoke(cli, ["render", *map(str, args), "--backend", "torch"], catch_exceptions=False)


def read_video(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened(), f"OpenCV cannot open {path}"
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[:, :, ::-1])  # BGR -> RGB
    cap.release()
    return frames


def one_error_line(res, *words):
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("splatk: error: "), res.stderr
    assert all(w in lines[0] for w in words), lines[0]


@pytest.mark.parametrize("path", ["orbit", "spiral"])
def test_orbit_and_spiral_have_the_frames_and_size_asked_for(run, tmp_path, path):
    out = tmp_path / f"{path}.mp4"
    res = render(run, "--path", path, "--frames", 12, "--size", "48x32", "--out", out)
    assert res.exit_code == 0, res.output
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    assert (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))) == (48, 32)
    assert cap.get(cv2.CAP_PROP_FOURCC) and int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") in (b"avc1", b"h264")
    frames = read_video(out)
    assert len(frames) == 12 and frames[0].shape == (32, 48, 3)
    # the scene is in view: frames are not the plain background, and the camera moves
    assert all(float(f.astype(float).std()) > 10 for f in frames)
    assert np.abs(frames[0].astype(float) - frames[3].astype(float)).mean() > 2


def test_test_path_is_the_test_views_as_eval_renders_them(run, tmp_path):
    out = tmp_path / "test.mp4"
    res = render(run, "--path", "test", "--crf", 0, "--out", out)
    assert res.exit_code == 0, res.output
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], test_every=meta["test_every"], background=tuple(meta["background"]))
    frames = read_video(out)
    assert len(frames) == len(scene.test) == 2 and frames[0].shape == (32, 32, 3)
    bg = torch.tensor(scene.background, dtype=torch.float32)
    with torch.no_grad():
        for frame, cam in zip(frames, scene.test):
            ref = model.render(cam, bg, backend=backends.get("torch", "cpu")).image.clamp(0, 1).numpy() * 255
            # x264 at crf 0 is lossless in YUV; what differs is 4:2:0 chroma and the RGB <-> YUV rounding
            assert np.abs(frame.astype(float) - ref).mean() < 6, cam.name


def test_path_file(run, tmp_path):
    _, meta = load_model(run / "model.pt")
    cams = load_scene(meta["scene"], load_images=False).train[:3]
    entries = [{"camera_to_world": torch.linalg.inv(c.world_to_cam.double()).tolist(), "fx": c.fx, "fy": c.fy,
                "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height} for c in cams]
    path = tmp_path / "cams.json"
    path.write_text(json.dumps(entries))
    out = tmp_path / "file.mp4"
    assert render(run, "--path", path, "--out", out).exit_code == 0
    assert len(read_video(out)) == 3
    out = tmp_path / "file8.mp4"
    assert render(run, "--path", path, "--frames", 8, "--size", "64x64", "--out", out).exit_code == 0
    frames = read_video(out)
    assert len(frames) == 8 and frames[0].shape == (64, 64, 3)


def test_refuses_to_overwrite(run, tmp_path):
    out = tmp_path / "v.mp4"
    out.write_bytes(b"someone's video")
    one_error_line(render(run, "--frames", 2, "--out", out), str(out), "exists", "--overwrite")
    assert out.read_bytes() == b"someone's video"
    assert render(run, "--frames", 2, "--out", out, "--overwrite").exit_code == 0
    assert len(read_video(out)) == 2
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"], "a temporary file was left behind"


def test_bad_input_is_one_line(run, tmp_path):
    one_error_line(render(run, "--size", "47x32", "--out", tmp_path / "a.mp4"), "even", "--size 46x32")
    one_error_line(render(run, "--out", tmp_path / "a.gif"), "a.gif", ".mp4")
    one_error_line(render(run, "--path", "circle", "--out", tmp_path / "a.mp4"), "circle", "orbit, spiral, test")
    bad = tmp_path / "bad.json"
    bad.write_text("[1]")
    one_error_line(render(run, "--path", bad, "--out", tmp_path / "a.mp4"), str(bad), "entry 0")
    assert not list(tmp_path.glob("*.mp4"))


def test_plain_progress_lines(run, tmp_path):
    res = render(run, "--frames", 4, "--log-every", 0, "--out", tmp_path / "v.mp4")
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("render ")]
    assert lines[-1].startswith("render 4/4 (100%)") and "it/s" in lines[-1] and "\x1b" not in res.stderr
