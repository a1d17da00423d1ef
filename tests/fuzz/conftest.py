"""Hypothesis profiles, a memory cap and tiny base scenes for the fuzz tests.

Profiles (examples per test; the ``long`` one totals more than 10,000 inputs over this folder):

    ci    the default: the folder runs in well under a minute
    long  ``pytest tests/fuzz --hypothesis-profile=long`` or ``SPLATK_FUZZ_PROFILE=long pytest tests/fuzz``

(``--hypothesis-profile`` needs this folder on the command line, so that this file is read
before hypothesis looks the profile up.)

Every test runs with the address space capped at what the process used when it started plus
:data:`MEMORY_HEADROOM`, and with the loaders told the machine has :data:`LOADER_MEMORY`, so
an input that makes a loader allocate past what its own image cap allows fails with MemoryError
instead of swapping the machine.
"""
from __future__ import annotations

import os
import resource
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from splatk.data import _common

# the bound on one input is generous (a loaded machine took 14 s for one tiny scene), a hang still fails
_COMMON = dict(deadline=60_000, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
               print_blob=True)
settings.register_profile("ci", max_examples=80, derandomize=True, **_COMMON)
settings.register_profile("long", max_examples=1500, **_COMMON)
settings.load_profile(os.environ.get("SPLATK_FUZZ_PROFILE", "ci"))

MEMORY_HEADROOM = 3 << 30
#: the memory the loaders' image cap is computed from during fuzzing: decoding may use half
LOADER_MEMORY = 2 << 30


def _address_space() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status")


@pytest.fixture(autouse=True)
def memory_cap(monkeypatch):
    monkeypatch.setattr(_common, "physical_memory_bytes", lambda: LOADER_MEMORY)
    if not Path("/proc/self/status").is_file():
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _address_space() + MEMORY_HEADROOM
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@pytest.fixture(scope="package")
def demo_base(tmp_path_factory) -> Path:
    """A 5-view, 16-pixel NeRF-synthetic scene (4 train + 1 test); copied, never modified."""
    from splatk.data.synthetic import make_demo_scene

    return make_demo_scene(tmp_path_factory.mktemp("fuzz_demo"), num_views=5, size=16)


def _tiny_colmap(root: Path, text: bool) -> Path:
    """Three 16x12 PINHOLE views of five points, as ``root/sparse/0`` + ``root/images``, in the
    layout of COLMAP < 3.12 (no rigs / frames files), which most datasets have."""
    import cv2
    import pycolmap

    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    (root / "images").mkdir(parents=True)
    for i in range(1, 4):
        rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_id(i, pycolmap.CameraModelId.PINHOLE,
                                                                             20.0, 16, 12))
        im = pycolmap.Image(name=f"img_{i:02d}.png", camera_id=i, image_id=i)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0.0, 0.0, 1.0])), np.array([0.1 * i, 0.0, 4.0]))
        rec.add_image_with_trivial_frame(im, pose)
        cv2.imwrite(str(root / "images" / im.name), rng.integers(0, 255, (12, 16, 3), dtype=np.uint8))
    for _ in range(5):
        rec.add_point3D(rng.normal(size=3), pycolmap.Track(), rng.integers(0, 255, 3).astype(np.uint8))
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(model))
    for name in ("rigs", "frames"):
        for f in model.glob(f"{name}.*"):
            f.unlink()
    return root


@pytest.fixture(scope="package")
def colmap_text_base(tmp_path_factory) -> Path:
    return _tiny_colmap(tmp_path_factory.mktemp("fuzz_colmap_txt"), text=True)


@pytest.fixture(scope="package")
def colmap_bin_base(tmp_path_factory) -> Path:
    return _tiny_colmap(tmp_path_factory.mktemp("fuzz_colmap_bin"), text=False)
