"""`splatk view RUN`: frames drawn by splatk's engine exactly as `eval` draws the views, served
by viser over HTTP; without viser, one line naming the install command."""
from __future__ import annotations

import math
import signal
import sys
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk import backends
from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.models.io import load_model
from splatk.stages.fit import FitConfig, run_fit
from splatk.stages.view import FramePlanner, RunView, camera_labels, frame_size
from splatk.train.trainer import TrainConfig
from splatk_cli.main import cli
from tests.scenes import orbit_cameras
from tests.viewer_process import start_viewer, stop_viewer


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("view")
    scene = make_demo_scene(tmp / "scene", num_views=16, size=32)
    cfg = FitConfig(sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=40, budget=300, init="random", backend="torch"))
    return run_fit(scene, tmp / "run", cfg).path


class FakeClient:
    """What `draw` reads of a viser client: its camera, and where the image goes."""

    def __init__(self, wxyz, position, fov, width, height):
        self.camera = SimpleNamespace(wxyz=wxyz, position=position, fov=fov, image_width=width, image_height=height)
        self.images = []
        self.scene = SimpleNamespace(set_background_image=lambda image, **kw: self.images.append(image))


def _client_at(cam, width=None, height=None):
    from viser import transforms

    R_c2w = cam.world_to_cam[:3, :3].double().T.numpy()
    return FakeClient(transforms.SO3.from_matrix(R_c2w).wxyz, cam.center.double().numpy(),
                      2 * math.atan(cam.height / (2 * cam.fy)), width or cam.width, height or cam.height)


def test_the_viewer_draws_a_view_as_eval_does(run):
    pytest.importorskip("viser")
    from splatk_cli.view import draw

    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], test_every=meta["test_every"], background=tuple(meta["background"]))
    cam = scene.test[0]
    assert (cam.fx, cam.cx, cam.cy) == (cam.fy, cam.width / 2, cam.height / 2)  # what a viser camera can express
    client = _client_at(cam)
    draw(client, RunView(run, backend="torch"), max_size=960)
    (image,) = client.images
    with torch.no_grad():
        ref = model.render(cam, torch.tensor(scene.background), backend=backends.get("torch", "cpu")).image
    ref = (ref.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    assert image.shape == ref.shape == (32, 32, 3)
    assert np.abs(image.astype(int) - ref.astype(int)).max() <= 1
    assert float(image.astype(float).std()) > 10  # the scene, not the background


def test_the_image_is_capped_at_max_size(run):
    pytest.importorskip("viser")
    from splatk_cli.view import draw

    model, meta = load_model(run / "model.pt")
    client = _client_at(load_scene(meta["scene"], load_images=False).train[0], width=1000, height=500)
    draw(client, RunView(run, backend="torch"), max_size=64)
    assert client.images[0].shape == (32, 64, 3)


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_serves_the_viewer_and_stops_on_ctrl_c_or_sigterm(run, stop):
    pytest.importorskip("viser")
    viewer = start_viewer(run, "--backend", "torch")
    try:
        with urllib.request.urlopen(viewer.url, timeout=10) as r:
            page = r.read().decode(errors="replace")
        assert "<html" in page.lower()
    finally:
        code, err = stop_viewer(viewer, stop)
    assert code == 0, err
    assert viewer.url.rstrip("/") in err  # the address it serves, as it printed it
    assert "Traceback" not in err and "Aborted" not in err, err


def test_without_viser_one_line_names_the_install(run, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    res = CliRunner().invoke(cli, ["view", str(run)], catch_exceptions=False)
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and 'pip install "splatk[view]"' in lines[0], res.stderr


def test_a_pose_puts_the_viewer_exactly_at_the_camera(run):
    view = RunView(run, backend="torch")
    for cam in (view.cameras["test/r_0.png"], view.start):
        pose = view.pose(cam)
        forward = pose["look_at"] - pose["position"]
        forward /= np.linalg.norm(forward)
        up = pose["up"] / np.linalg.norm(pose["up"])
        R_c2w = np.stack([np.cross(-up, forward), -up, forward], axis=1)  # OpenCV axes: x right, y down, z ahead
        seen = RunView.camera(R_c2w, pose["position"], pose["fov_y"], cam.width, cam.height)
        assert torch.allclose(seen.world_to_cam, cam.world_to_cam, atol=1e-5)
        assert (seen.fx, seen.fy) == pytest.approx((cam.fx, cam.fy))
        # the orbit pivot lies ahead of the camera, near the scene rather than on the lens
        assert np.dot(pose["look_at"] - pose["position"], forward) > 1.0


def test_cameras_are_listed_test_views_first_and_by_unique_names(run):
    view = RunView(run, backend="torch", start="test/r_8.png")
    names = list(view.cameras)
    assert names[:2] == ["test/r_0.png", "test/r_8.png"] and len(names) == 16
    assert view.start is view.cameras["test/r_8.png"]
    cams = orbit_cameras(3)
    labels = camera_labels(cams[:1], cams)  # a name in both splits (NeRF-synthetic's r_0 in train and test)
    assert list(labels) == [f"test: {cams[0].name}", f"train: {cams[0].name}", cams[1].name, cams[2].name]


def test_an_unknown_start_camera_is_one_line_naming_the_cameras(run):
    pytest.importorskip("viser")
    res = CliRunner().invoke(cli, ["view", str(run), "--camera", "nope.png", "--port", "0"])
    assert res.exit_code == 2, res.output
    (line,) = res.stderr.strip().splitlines()
    assert line.startswith(f"splatk: error: {run}: ") and "'nope.png'" in line and "test/r_0.png" in line


def test_frames_shrink_to_keep_the_frame_rate_while_moving_and_sharpen_at_rest():
    planner = FramePlanner(max_size=800, target_s=0.1, min_size=64, rest_s=0.25)
    assert planner.next_size(stamp=1.0, now=0.0) == 800  # first frame: full size until timed
    planner.drawn(800, 1.6)  # 16x too slow: the ideal size is 800 / 4 = 200
    assert planner.next_size(1.0, 0.1) is None  # camera unchanged, not yet at rest
    sizes = []
    for i in range(2, 12):  # the camera keeps moving; each frame takes time in proportion to its pixels
        size = planner.next_size(float(i), 0.1 * i)
        sizes.append(size)
        planner.drawn(size, 1.6 * (size / 800) ** 2)
    assert sizes[0] < 800 and sizes == sorted(sizes, reverse=True)
    assert abs(sizes[-1] - 200) <= 10  # settles where a frame takes the target time
    assert planner.next_size(11.0, 1.2) is None  # at rest for less than rest_s
    assert planner.next_size(11.0, 1.4) == 800  # at rest: one full-size frame
    assert planner.next_size(11.0, 5.0) is None  # and nothing more until the camera moves


def test_a_fast_renderer_keeps_full_size_frames_and_small_windows_need_no_second_frame():
    planner = FramePlanner(max_size=400, target_s=0.1)
    for i in range(5):
        size = planner.next_size(float(i), 0.1 * i)
        assert size == 400
        planner.drawn(size, 0.01)
    assert planner.next_size(4.0, 10.0) is None  # already sharp
    slow = FramePlanner(max_size=400, target_s=0.1, min_size=64)
    for i in range(3):
        size = slow.next_size(float(i), 0.1 * i)
        slow.drawn(size, 100.0)
    assert size == 64  # never below min_size
    assert slow.next_size(3.0, 0.3) == 64
    slow.drawn(64, 0.01, full=True)  # the window is only 64 pixels wide: that frame was full size
    assert slow.next_size(3.0, 10.0) is None


def test_frame_size_keeps_the_aspect_and_never_enlarges():
    assert frame_size(1000, 500, 64) == (64, 32)
    assert frame_size(30, 20, 960) == (30, 20)
    assert frame_size(1000, 1, 16) == (16, 2)
