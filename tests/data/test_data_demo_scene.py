"""The built-in demo scene: deterministic, fast, loads through load_scene with the right geometry."""
from __future__ import annotations

import time

import numpy as np

from splatk.data import load_scene, scene_summary
from splatk.data.synthetic import make_demo_scene


def test_default_demo_scene(tmp_path):
    t = time.perf_counter()
    root = make_demo_scene(tmp_path / "demo")
    assert time.perf_counter() - t < 5.0
    sc = load_scene(root)
    assert (len(sc.train), len(sc.test)) == (21, 3)
    assert sc.background == (1.0, 1.0, 1.0) and sc.points.shape == (0, 3)
    assert scene_summary(sc)["resolution"] == "96x96"
    for c in sc.cameras:
        img = c.image.numpy()
        assert img.shape == (96, 96, 3)
        white = (img == 255).all(axis=2).mean()
        assert 0.3 < white < 0.97, c.name  # white background and some objects
        assert img.std() > 20
        # the checkered sphere sits at the origin: the image centre is not background
        assert not (img[46:50, 46:50] == 255).all(), c.name
        z = (c.world_to_cam[:3, 3]).norm().item()
        assert abs(z - 4.0) < 1e-4  # camera 4 units from the origin


def test_demo_scene_is_deterministic(tmp_path):
    a = make_demo_scene(tmp_path / "a", num_views=4, size=24, seed=3)
    b = make_demo_scene(tmp_path / "b", num_views=4, size=24, seed=3)
    c = make_demo_scene(tmp_path / "c", num_views=4, size=24, seed=4)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    assert any((a / f).read_bytes() != (c / f).read_bytes() for f in files if f.suffix == ".png")


def test_demo_geometry_matches_loader(demo_dir):
    """The loaded cameras see the scene where it was rendered: the origin (centre of the
    checkered sphere) projects to the image centre and its pixel is covered in every view."""
    sc = load_scene(demo_dir)
    for c in sc.cameras:
        assert np.allclose([c.cx, c.cy], [16, 16]) and c.fx == c.fy
        M = c.world_to_cam.double().numpy()
        Xc = M[:3, 3]  # the origin in camera coordinates
        assert Xc[2] > 0
        u, v = Xc[:2] / Xc[2] * [c.fx, c.fy] + [c.cx, c.cy]
        assert abs(u - 16) < 1e-3 and abs(v - 16) < 1e-3
        assert (c.image.numpy()[int(v), int(u)] != 255).any()
        # the world z axis (up in the generator) points up in every image: y decreases
        top = M[:3, :3] @ np.array([0.0, 0.0, 0.5]) + Xc
        assert top[1] / top[2] * c.fy + c.cy < v


def test_downscaled_demo(demo_dir):
    sc = load_scene(demo_dir, downscale=2)
    assert all(c.image.shape == (16, 16, 3) for c in sc.cameras)
    full = load_scene(demo_dir, load_images=False)
    assert sc.train[0].fx == full.train[0].fx / 2
