"""What every fuzzed scene load must satisfy (imported by the fuzz tests)."""
from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from splatk.data import load_scene
from splatk.errors import InputError


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@contextmanager
def scene_copy(base: Path) -> Iterator[tuple[Path, Path]]:
    """A fresh copy of ``base`` as ``tmp/scene`` beside ``tmp/outside`` (a PNG and a text file that
    a well-behaved loader never changes); yields (scene, outside)."""
    with tempfile.TemporaryDirectory(prefix="splatk-fuzz-") as tmp:
        scene = Path(shutil.copytree(base, Path(tmp) / "scene", symlinks=True))
        outside = Path(tmp) / "outside"
        outside.mkdir()
        shutil.copy(next(base.rglob("*.png")), outside / "photo.png")
        (outside / "notes.txt").write_text("not part of the scene\n")
        yield scene, outside


def check_scene(scene) -> None:
    """What a returned Scene promises: finite float32 poses and positive finite intrinsics,
    images of the stated size, at least one camera."""
    assert scene.cameras
    for c in scene.cameras:
        assert c.width >= 1 and c.height >= 1
        assert all(np.isfinite(v) for v in (c.fx, c.fy, c.cx, c.cy)) and c.fx > 0 and c.fy > 0, c
        assert bool(c.world_to_cam.isfinite().all()) and tuple(c.world_to_cam.shape) == (4, 4)
        if c.image is not None:
            assert tuple(c.image.shape) == (c.height, c.width, 3)
    assert bool(scene.points.isfinite().all())




def loads_or_refuses(scene_dir: Path, outside: Path, **kwargs) -> str:
    """``load_scene(scene_dir)`` returns a valid Scene or raises a one-line InputError with a fix;
    nothing in the scene folder or beside it changes. Returns "ok" or "refused" (for ``event``)."""
    before = snapshot(scene_dir.parent)
    try:
        scene = load_scene(scene_dir, **kwargs)
    except InputError as e:
        assert "\n" not in str(e) and e.fix, repr(e)
        outcome = "refused"
    else:
        check_scene(scene)
        outcome = "ok"
    assert snapshot(scene_dir.parent) == before, "a file in or beside the scene folder changed"
    return outcome
