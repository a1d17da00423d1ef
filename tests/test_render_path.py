"""Camera paths for videos: the look-at centre, orbit and spiral geometry, and path files."""
from __future__ import annotations

import json
import math

import pytest
import torch

from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.errors import InputError
from splatk.render_path import cameras_from_json, look_at, look_at_centre, orbit_path, spiral_path


@pytest.fixture(scope="module")
def cameras(tmp_path_factory):
    # the demo's cameras sit on a hemisphere of radius 4 around the origin, looking at it
    scene = load_scene(make_demo_scene(tmp_path_factory.mktemp("paths") / "scene", num_views=16, size=16),
                       load_images=False)
    return scene.train


def _forward(cam):
    return cam.world_to_cam[:3, :3].double().T[:, 2]


def test_look_at_centre_is_where_the_axes_meet(cameras):
    assert torch.allclose(look_at_centre(cameras), torch.zeros(3, dtype=torch.float64), atol=1e-3)


def test_look_at_faces_the_target_upright():
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in ([0, -5, 1], [0, 0, 1], [0, 0, 1]))
    w2c = look_at(eye, target, up)
    assert torch.allclose(w2c[:3, :3] @ w2c[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(w2c[:3, :3] @ target + w2c[:3, 3], torch.tensor([0, 0, 5.0], dtype=torch.float64))
    assert torch.allclose(w2c[:3, :3].T[:, 1], -up)  # image y (down) is world down


def test_orbit_circles_the_centre(cameras):
    path = orbit_path(cameras, 24)
    assert len(path) == 24
    centres = torch.stack([c.center.double() for c in path])
    dists = centres.norm(dim=-1)
    assert float(dists.std()) < 1e-4 and abs(float(dists.mean()) - 4.0) < 0.2
    for cam in path:  # every frame looks at the centre
        to_centre = -cam.center.double() / cam.center.double().norm()
        assert float(_forward(cam) @ to_centre) > 0.9999
    # a full turn at a steady pace: equal chords between frames, the last one back to the first
    chords = (torch.roll(centres, -1, 0) - centres).norm(dim=-1)
    assert float(chords.std()) < 1e-4 * float(chords.mean())
    assert torch.allclose(chords.mean(), 2 * (centres[:, :2].norm(dim=-1).mean()) * math.sin(math.pi / 24), rtol=0.05)


def test_spiral_stays_near_the_first_camera_looking_at_the_centre(cameras):
    ref = sorted(cameras, key=lambda c: c.name)[0]
    path = spiral_path(cameras, 30, radius=0.15)
    offsets = torch.stack([c.center.double() - ref.center.double() for c in path]).norm(dim=-1)
    assert float(offsets.max()) <= 0.15 * 4.0 * math.sqrt(2) + 1e-3 and float(offsets.max()) > 0.3
    for cam in path:
        to_centre = -cam.center.double() / cam.center.double().norm()
        assert float(_forward(cam) @ to_centre) > 0.9999


def test_path_file_round_trip(tmp_path, cameras):
    entries = []
    for i, cam in enumerate(cameras[:3]):
        m = cam.world_to_cam.double()
        key, value = ("camera_to_world", torch.linalg.inv(m)) if i % 2 else ("world_to_cam", m)
        entries.append({key: value.tolist(), "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                        "width": cam.width, "height": cam.height})
    f = tmp_path / "path.json"
    f.write_text(json.dumps(entries))
    got = cameras_from_json(f)
    assert len(got) == 3
    for a, b in zip(got, cameras[:3]):
        assert torch.allclose(a.world_to_cam, b.world_to_cam, atol=1e-5)
        assert (a.width, a.height, a.fx, a.cy) == (b.width, b.height, b.fx, b.cy)


@pytest.mark.parametrize("content, problem", [
    ("{", "not a readable JSON file"),
    ("[]", "non-empty JSON list"),
    ('[{"fx": 1}]', "entry 0 lacks fy, cx, cy, width, height"),
    ('[{"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 4, "height": 4}]', "exactly one of"),
    ('[{"world_to_cam": [[1, 0], [0, 1]], "fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 4, "height": 4}]',
     "not an invertible 4x4"),
])
def test_bad_path_files_name_the_problem(tmp_path, content, problem):
    f = tmp_path / "bad.json"
    f.write_text(content)
    with pytest.raises(InputError, match=problem) as e:
        cameras_from_json(f)
    assert e.value.path == f and "world_to_cam" in e.value.fix
