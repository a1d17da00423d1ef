"""Loaders on the real scenes in ../shared/data: counts, splits, camera sanity and geometry.

The geometric checks catch pose / intrinsics / undistortion convention bugs: SfM points must
project onto the keypoints that observed them, matched SIFT features must lie on the epipolar
lines the loaded cameras predict, and undistorted pixels must equal the original image sampled
where the distorted camera model sends them.
"""
from __future__ import annotations

import json
import math
from functools import lru_cache

import cv2
import numpy as np
import pycolmap
import pytest

from splatk.data import load_scene, scene_summary
from splatk.data.types import Camera, Scene

pytestmark = pytest.mark.shared_data

# images per scene (SOURCES.md); lego has its own train / test lists
N_IMAGES = {"fox": 50, "cup": 77, "bonsai": 84, "beer_can": 71, "juicebox": 64, "kangaroo": 29}
COLMAP_SCENES = ("cup", "bonsai", "beer_can", "juicebox")
TRANSFORMS_SCENES = ("fox", "kangaroo", "lego")
ALL_SCENES = COLMAP_SCENES + TRANSFORMS_SCENES


@lru_cache(maxsize=None)
def _load_cameras(root: str, downscale: float) -> Scene:
    return load_scene(root, downscale=downscale, load_images=False)


@lru_cache(maxsize=3)  # decoded scenes are 50-110 MB each: keep only the last few
def _load_with_images(root: str, downscale: float) -> Scene:
    return load_scene(root, downscale=downscale, load_images=True)


@pytest.fixture(scope="module", autouse=True)
def _free_scenes():
    yield
    _load_cameras.cache_clear()
    _load_with_images.cache_clear()


def scene(shared_data, name: str, load_images: bool = False, downscale: float = 1.0) -> Scene:
    path = shared_data / name
    if not path.is_dir():
        pytest.skip(f"{path} not present")
    return (_load_with_images if load_images else _load_cameras)(str(path), downscale)


def project(cam: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth [N], pixel [N, 2]) of world points X [N, 3] (half-pixel convention)."""
    M = cam.world_to_cam.double().numpy()
    Xc = X @ M[:3, :3].T + M[:3, 3]
    z = Xc[:, 2]
    uv = Xc[:, :2] / z[:, None] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    return z, uv


def visible(cam: Camera, X: np.ndarray) -> np.ndarray:
    z, uv = project(cam, X)
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_SCENES)
def test_counts_and_split(shared_data, name):
    sc = scene(shared_data, name)
    if name == "lego":
        assert (len(sc.train), len(sc.test)) == (50, 25)
        assert all(c.name.startswith("train/") for c in sc.train)
        assert all(c.name.startswith("test/") for c in sc.test)
        assert sc.background == (1.0, 1.0, 1.0)
        return
    n = N_IMAGES[name]
    assert len(sc.test) == math.ceil(n / 8) and len(sc.train) == n - len(sc.test)
    names = sorted(c.name for c in sc.cameras)
    assert [c.name for c in sc.test] == names[::8]  # every 8th in name order, starting at 0
    assert sc.source == ("colmap" if name in COLMAP_SCENES else "transforms")
    s = scene_summary(sc)
    assert (s["train"], s["test"]) == (len(sc.train), len(sc.test)) and s["points"] == sc.points.shape[0]


@pytest.mark.parametrize("name", ALL_SCENES)
def test_cameras_sane(shared_data, name):
    sc = scene(shared_data, name, load_images=True)
    for c in sc.cameras:
        assert c.image is not None and c.image.dtype.is_floating_point is False
        assert tuple(c.image.shape) == (c.height, c.width, 3), c.name
        assert c.fx > 0.3 * c.width and c.fy > 0.3 * c.width and abs(c.fx / c.fy - 1) < 0.02
        assert 0.3 * c.width < c.cx < 0.7 * c.width and 0.3 * c.height < c.cy < 0.7 * c.height
        M = c.world_to_cam.double()
        assert M.shape == (4, 4) and bool(M.isfinite().all())
        R = M[:3, :3].numpy()
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-5) and abs(np.linalg.det(R) - 1) < 1e-5
        assert np.allclose(M[3].numpy(), [0, 0, 0, 1])
    assert float(sc.cameras[0].image.float().std()) > 5  # not blank
    assert sc.extent > 0


@pytest.mark.parametrize("name,median_min", [("cup", 0.5), ("beer_can", 0.5), ("juicebox", 0.5), ("bonsai", 0.15)])
def test_colmap_points_in_view(shared_data, name, median_min):
    """SfM points land in front of and inside the train cameras (bonsai is a 360 room: fewer)."""
    sc = scene(shared_data, name)
    P = sc.points.double().numpy()
    assert P.shape[0] > 1000 and sc.point_colors.shape == sc.points.shape
    assert 0 <= float(sc.point_colors.min()) and float(sc.point_colors.max()) <= 1
    frac = np.array([visible(c, P).mean() for c in sc.train])
    assert np.median(frac) > median_min
    if name != "bonsai":
        assert frac.max() > 0.8


@pytest.mark.parametrize("name", ["cup", "beer_can", "bonsai"])
def test_colmap_tracks_reproject(shared_data, name):
    """Each 3D point projects (with the loaded, undistorted pinhole) onto the undistorted keypoint
    that observed it: checks pose convention, undistortion, ROI crop and pixel-centre handling."""
    sc = scene(shared_data, name)
    rec = pycolmap.Reconstruction(str(shared_data / name / "sparse" / "0"))
    by_name = {im.name: im for im in rec.images.values()}
    medians = []
    for c in sc.cameras[::4]:
        im = by_name[c.name]
        obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs])
        X = np.array([rec.points3D[o[1]].xyz for o in obs])
        inside = visible(c, X)
        assert inside.mean() > 0.95, c.name
        _, uv = project(c, X)
        normalised = np.asarray(rec.cameras[im.camera_id].cam_from_img(xy))  # undo COLMAP distortion
        kp = normalised * [c.fx, c.fy] + [c.cx, c.cy]
        medians.append(np.median(np.linalg.norm(kp - uv, axis=1)))
    assert np.median(medians) < 1.0 and max(medians) < 2.0, medians


def test_lego_origin_at_image_centre(shared_data):
    sc = scene(shared_data, "lego")
    for c in sc.cameras:
        z, uv = project(c, np.zeros((1, 3)))
        assert z[0] > 0
        assert np.allclose(uv[0], [c.width / 2, c.height / 2], atol=0.02 * c.width)


def _epipolar_median(c1: Camera, c2: Camera) -> tuple[int, float]:
    """(number of SIFT matches, median distance in px of c2's keypoints to their epipolar lines)."""
    sift = cv2.SIFT_create(2000, contrastThreshold=0.02)
    k1, d1 = sift.detectAndCompute(cv2.cvtColor(c1.image.numpy(), cv2.COLOR_RGB2GRAY), None)
    k2, d2 = sift.detectAndCompute(cv2.cvtColor(c2.image.numpy(), cv2.COLOR_RGB2GRAY), None)
    if d1 is None or d2 is None:
        return 0, float("inf")
    good = [a for a, b in cv2.BFMatcher().knnMatch(d1, d2, k=2) if a.distance < 0.7 * b.distance]
    if len(good) < 8:
        return len(good), float("inf")
    x1 = np.array([k1[m.queryIdx].pt for m in good]) + 0.5  # OpenCV -> half-pixel centres
    x2 = np.array([k2[m.trainIdx].pt for m in good]) + 0.5
    M = c2.world_to_cam.double().numpy() @ np.linalg.inv(c1.world_to_cam.double().numpy())
    R, t = M[:3, :3], M[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(c2.K.double().numpy()).T @ tx @ R @ np.linalg.inv(c1.K.double().numpy())
    lines = np.c_[x1, np.ones(len(x1))] @ F.T
    d = np.abs((lines * np.c_[x2, np.ones(len(x2))]).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
    return len(good), float(np.median(d))


@pytest.mark.parametrize("name", ["fox", "kangaroo"])
def test_transforms_epipolar_geometry(shared_data, name):
    """SIFT matches between neighbouring views lie on the loaded cameras' epipolar lines
    (flipped axes, a wrong focal length or a bad undistortion give tens of pixels)."""
    sc = scene(shared_data, name, load_images=True)
    cams = sc.train
    centres = np.stack([c.center.numpy() for c in cams])
    results = []
    for i in (0, 6, 12):
        d = np.linalg.norm(centres - centres[i], axis=1)
        d[i] = np.inf
        results.append(_epipolar_median(cams[i], cams[int(d.argmin())]))
    usable = [m for n, m in results if n >= 30]
    assert len(usable) >= 2, results
    assert max(usable) < 1.0, results


def test_transforms_cameras_look_at_object(shared_data):
    """fox / kangaroo: the point nearest to all optical axes is in front of every camera."""
    for name in ("fox", "kangaroo"):
        sc = scene(shared_data, name)
        A, b = np.zeros((3, 3)), np.zeros(3)
        for c in sc.cameras:
            axis = c.world_to_cam[2, :3].double().numpy()
            P = np.eye(3) - np.outer(axis, axis)
            A += P
            b += P @ c.center.double().numpy()
        X = np.linalg.solve(A, b)[None]
        assert all(visible(c, X)[0] for c in sc.cameras), name


def _undistortion_error(cam: Camera, K: np.ndarray, dist: np.ndarray) -> float:
    """Mean |undistorted pixel - original image at the distorted position of that pixel's ray|."""
    orig = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[:, :, ::-1]
    rng = np.random.default_rng(0)
    ui = rng.integers(4, cam.width - 4, 2000)
    vi = rng.integers(4, cam.height - 4, 2000)
    rays = np.stack([(ui + 0.5 - cam.cx) / cam.fx, (vi + 0.5 - cam.cy) / cam.fy, np.ones(len(ui))], 1)
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV pixel centres are integers
    p, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_cv, dist)
    p = p.reshape(1, -1, 2).astype(np.float32)
    sampled = cv2.remap(np.ascontiguousarray(orig).astype(np.float32), p[..., 0].copy(), p[..., 1].copy(),
                        cv2.INTER_LINEAR)[0]
    return float(np.abs(sampled - cam.image.numpy()[vi, ui].astype(np.float32)).mean())


def test_undistortion_fox_opencv(shared_data):
    """fox: OPENCV (k1, k2, p1, p2) in transforms.json -> pinhole; pixels match the distorted model."""
    meta = json.loads((shared_data / "fox" / "transforms.json").read_text())
    K = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1.0]])
    dist = np.array([meta["k1"], meta["k2"], meta["p1"], meta["p2"]])
    sc = scene(shared_data, "fox", load_images=True)
    for c in sc.train[:2]:
        assert (c.width, c.height) != (405, 720) and c.width <= 405 and c.height <= 720  # cropped to ROI
        assert tuple(c.image.shape) == (c.height, c.width, 3)
        assert abs(c.fx / meta["fl_x"] - 1) < 0.05
        err = _undistortion_error(c, K, dist)
        assert err < 1.0, err  # a 1 px shift of the principal point gives about 4.5


@pytest.mark.parametrize("name", ["bonsai", "beer_can"])
def test_undistortion_colmap_simple_radial(shared_data, name):
    rec = pycolmap.Reconstruction(str(shared_data / name / "sparse" / "0"))
    sc = scene(shared_data, name, load_images=True)
    by_name = {im.name: im for im in rec.images.values()}
    for c in sc.train[:2]:
        cam = rec.cameras[by_name[c.name].camera_id]
        assert cam.model.name == "SIMPLE_RADIAL"
        f, cx, cy, k = cam.params
        assert c.width <= cam.width and c.height <= cam.height
        assert tuple(c.image.shape) == (c.height, c.width, 3)
        err = _undistortion_error(c, np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.array([k, 0, 0, 0]))
        assert err < 1.0, err


@pytest.mark.parametrize("name", ["cup", "bonsai"])
def test_downscale_halves(shared_data, name):
    full = scene(shared_data, name)
    half = scene(shared_data, name, load_images=True, downscale=2.0)
    for a, b in zip(full.cameras[:5], half.cameras[:5]):
        assert b.width == int(a.width / 2 + 0.5) and b.height == int(a.height / 2 + 0.5)
        assert tuple(b.image.shape) == (b.height, b.width, 3)
        for key, size in (("fx", a.width), ("cx", a.width), ("fy", a.height), ("cy", a.height)):
            assert getattr(b, key) == pytest.approx(getattr(a, key) / 2, rel=2.0 / size), key
        assert np.allclose(a.world_to_cam.numpy(), b.world_to_cam.numpy())
    assert half.points.shape == full.points.shape
