"""`splatk render`: a video of a run along a camera path, an H.264 MP4.

Paths (``splatk.render_path``): ``orbit`` and ``spiral`` around the train cameras' look-at
centre, ``test`` (the test cameras in order) or a JSON path file. Frames are rendered as
``eval`` renders them (the same model, backend object and background), then encoded by the
ffmpeg binary that the ``imageio-ffmpeg`` wheel ships, into a temporary file renamed over
``out`` when complete.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .. import backends
from ..data import load_scene
from ..data.types import Camera
from ..device import resolve_device
from ..errors import InputError
from ..models.io import load_model
from ..outputs import check_output_file
from ..render_path import cameras_from_json, interpolate_cameras, orbit_path, spiral_path

PATHS = ("orbit", "spiral", "test")


@dataclass
class VideoConfig:
    """What `splatk render` draws."""

    path: str = "orbit"
    """orbit, spiral, test, or a JSON path file (see ``splatk.render_path.cameras_from_json``)."""
    frames: int | None = None
    """Frames to render; None: 120 for orbit and spiral, one per camera for test and path files
    (any other number interpolates through those cameras)."""
    size: tuple[int, int] | None = None
    """(width, height) in pixels, even (H.264's 4:2:0 chroma); None: the first camera's size,
    rounded down to even. Intrinsics scale with it."""
    fps: float = 30.0
    """Frames per second of the video."""
    crf: int = 18
    """x264 constant rate factor: 0 lossless .. 51 worst; 18 looks lossless to most eyes."""
    backend: str = "auto"
    """Rasteriser backend, as for `splatk eval`."""
    device: str = "cpu"
    """Torch device to render on."""


def render_video(run: str | Path, out: str | Path, cfg: VideoConfig = VideoConfig(), overwrite: bool = False,
                 scene_path: str | Path | None = None,
                 on_frame: Callable[[int, int], None] | None = None) -> Path:
    """Render RUN's model along ``cfg.path`` into the MP4 ``out``; returns ``out``.

    Raises:
        InputError: ``out`` exists (without ``overwrite``) or is not an .mp4, a bad path name or
            file, an odd or non-positive size, or a scene the path needs that is not found.
    """
    run, out = Path(run), Path(out)
    if out.suffix.lower() != ".mp4":
        raise InputError(out, "the video is written as MP4", "give --out a name ending in .mp4")
    check_output_file(out, overwrite, inputs=(run / "model.pt",))
    _check_numbers(cfg)
    model, meta = load_model(run / "model.pt")
    cams = _path_cameras(cfg, meta, scene_path)
    size = cfg.size or (cams[0].width // 2 * 2, cams[0].height // 2 * 2)
    if min(size) < 2:
        raise InputError(None, f"frames of {size[0]}x{size[1]} pixels are too small for H.264", "pass --size")
    cams = [_resized(c, *size) for c in cams]
    dev = resolve_device(cfg.device, cfg.backend)
    renderer = backends.get(cfg.backend, dev)
    model = model.to(dev)
    bg = torch.tensor(run_background(meta, scene_path), dtype=torch.float32, device=dev)

    from imageio_ffmpeg import write_frames

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.{os.getpid()}.partial.mp4")
    writer = write_frames(str(tmp), size, fps=cfg.fps, codec="libx264", pix_fmt_in="rgb24",
                          pix_fmt_out="yuv420p", quality=None, macro_block_size=1,
                          output_params=["-crf", str(cfg.crf)], ffmpeg_log_level="error")
    try:
        writer.send(None)  # starts ffmpeg
        with torch.no_grad():
            for i, cam in enumerate(cams):
                img = model.render(cam, bg, backend=renderer).image.clamp(0, 1)
                writer.send(np.ascontiguousarray((img.cpu().numpy() * 255 + 0.5).astype(np.uint8)))
                if on_frame:
                    on_frame(i + 1, len(cams))
        writer.close()
        os.replace(tmp, out)
    finally:
        writer.close()
        tmp.unlink(missing_ok=True)
    return out


def _check_numbers(cfg: VideoConfig) -> None:
    if cfg.frames is not None and cfg.frames < 1:
        raise InputError(None, f"--frames {cfg.frames}: a video needs at least one frame", "e.g. --frames 120")
    if cfg.size is not None and (min(cfg.size) < 2 or cfg.size[0] % 2 or cfg.size[1] % 2):
        w, h = cfg.size
        raise InputError(None, f"--size {w}x{h}: H.264 (4:2:0) needs an even width and height of at least 2",
                         f"e.g. --size {max(2, w // 2 * 2)}x{max(2, h // 2 * 2)}")
    if not cfg.fps > 0:
        raise InputError(None, f"--fps {cfg.fps}: must be positive", "e.g. --fps 30")
    if not 0 <= cfg.crf <= 51:
        raise InputError(None, f"--crf {cfg.crf}: x264 takes 0 to 51", "e.g. --crf 18")


def _path_cameras(cfg: VideoConfig, meta: dict, scene_path) -> list[Camera]:
    if cfg.path not in PATHS:
        path = Path(cfg.path)
        if path.suffix.lower() != ".json" or not path.is_file():
            raise InputError(path, "not a path name nor a JSON path file",
                             f"use one of {', '.join(PATHS)} or a .json file of cameras")
        cams = cameras_from_json(path)
        return cams if cfg.frames in (None, len(cams)) else interpolate_cameras(cams, cfg.frames)
    scene = run_scene(meta, scene_path)
    if cfg.path == "test":
        if not scene.test:
            raise InputError(scene.root, "the scene has no test views", "use --path orbit or spiral")
        cams = scene.test
        return cams if cfg.frames in (None, len(cams)) else interpolate_cameras(cams, cfg.frames)
    if len(scene.train) < 2:
        raise InputError(scene.root, f"an {cfg.path} path needs at least two train cameras",
                         "use --path test or a JSON path file")
    make = orbit_path if cfg.path == "orbit" else spiral_path
    return make(scene.train, cfg.frames or 120)


def run_scene(meta: dict, scene_path):
    """The cameras (no images) of the scene a run was fitted on, as the run loaded it."""
    scene_path = scene_path or meta.get("scene")
    if not scene_path or not Path(scene_path).exists():
        raise InputError(scene_path, "scene folder of this run not found", "pass --scene, or a JSON path file")
    return load_scene(scene_path, downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                      background=tuple(meta["background"]) if meta.get("background") else None,
                      load_images=False, eval_split=meta.get("eval_split", "held-out"))


def run_background(meta: dict, scene_path) -> tuple[float, float, float]:
    """The RGB background the run was trained and is evaluated on."""
    if meta.get("background"):
        return tuple(meta["background"])
    return tuple(run_scene(meta, scene_path).background)


def _resized(cam: Camera, width: int, height: int) -> Camera:
    """``cam`` drawn at ``width`` x ``height``: the intrinsics scale with the image."""
    if (cam.width, cam.height) == (width, height):
        return cam
    sx, sy = width / cam.width, height / cam.height
    return Camera(cam.name, width, height, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy, cam.world_to_cam)
