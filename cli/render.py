"""`splatk render RUN --path orbit --out video.mp4`: a video of a run along a camera path."""
from __future__ import annotations

import re
from pathlib import Path

import click

from splatk.backends import backend_names
from splatk.stages.render_video import PATHS, VideoConfig, render_video

from .progress import DEFAULT_LOG_EVERY, frames_progress, stderr_console

_D = VideoConfig()


def _size(ctx, param, value):
    if value is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", value)
    if not m:
        raise click.BadParameter(f"{value!r} is not WIDTHxHEIGHT, e.g. 640x480")
    return int(m.group(1)), int(m.group(2))


@click.command("render")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="The MP4 file to write.")
@click.option("--path", "path_", default=_D.path, show_default=True, metavar=f"{'|'.join(PATHS)}|FILE.json",
              help="Camera path: orbit (a circle around the train cameras' look-at centre at their mean height "
                   "and distance), spiral (around the first train camera, looking at that centre), test (the "
                   "test views in order), or a JSON list of cameras, each {\"world_to_cam\" or "
                   "\"camera_to_world\": 4x4 (OpenCV axes), \"fx\", \"fy\", \"cx\", \"cy\", \"width\", \"height\"}.")
@click.option("--frames", type=int, help="Frames to render; other than the cameras' number, test and path files "
              "are interpolated. [default: 120 for orbit and spiral, one per camera otherwise]")
@click.option("--size", callback=_size, metavar="WxH", help="Frame size, even numbers (intrinsics scale with it). "
              "[default: the first camera's, rounded down to even]")
@click.option("--fps", type=float, default=_D.fps, show_default=True, help="Frames per second.")
@click.option("--crf", type=int, default=_D.crf, show_default=True,
              help="H.264 quality: x264's constant rate factor, 0 (lossless) to 51.")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), default=_D.backend, show_default=True,
              help="Rasteriser backend.")
@click.option("--device", default=_D.device, show_default=True, help="Torch device to render on, e.g. cpu or cuda.")
@click.option("--scene", type=click.Path(path_type=Path), help="Scene folder, if it moved since `fit`.")
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False,
              help="Replace --out if it exists (not read from the environment).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--log-every", type=click.FloatRange(min=0), default=DEFAULT_LOG_EVERY, show_default=True,
              metavar="SECONDS", help="When stderr is not a terminal: print a plain progress line this often "
              "instead of the bar.")
def command(run, out, path_, frames, size, fps, crf, backend, device, scene, overwrite, quiet, log_every):
    """Render RUN along a camera path into an H.264 MP4 video."""
    cfg = VideoConfig(path=path_, frames=frames, size=size, fps=fps, crf=crf, backend=backend, device=device)
    console = stderr_console()
    progress = None if quiet else frames_progress(console, log_every)
    task = {}

    def on_frame(done, total):
        if progress is None:
            return
        if "id" not in task:
            progress.start()
            task["id"] = progress.add_task("render", total=total, completed=0)
        progress.update(task["id"], completed=done)

    try:
        written = render_video(run, out, cfg, overwrite=overwrite, scene_path=scene, on_frame=on_frame)
    finally:
        if progress is not None:
            progress.stop()
    console.print(f"wrote {written}")
