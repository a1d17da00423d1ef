"""`splatk sfm IMAGES --out SCENE`: camera poses for unposed photos (COLMAP through pycolmap)."""
from __future__ import annotations

import json
from pathlib import Path

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from splatk.stages.sfm import CAMERA_MODES, run_sfm

_STEPS = {"features": "SIFT features", "matching": "exhaustive matching", "mapping": "incremental mapping",
          "undistortion": "undistortion"}


@click.command("sfm")
@click.argument("images", type=click.Path(path_type=Path))
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True,
              help="Scene folder to write: images/ (undistorted), sparse/0, sfm.json.")
@click.option("--camera-model", default="SIMPLE_RADIAL", show_default=True,
              help="COLMAP camera model to estimate (undistorted to PINHOLE at the end).")
@click.option("--camera-mode", type=click.Choice(list(CAMERA_MODES)), default="auto", show_default=True,
              help="Share one camera between all photos (single: video frames), give each its own "
                   "(per-image: internet photos), or decide from image size and EXIF (auto).")
@click.option("--max-image-size", type=int, default=1600, show_default=True,
              help="Longest side (px) the photos are scaled to for feature extraction.")
@click.option("--min-registered", type=int, default=3, show_default=True,
              help="Fail if fewer images than this get a pose.")
@click.option("--seed", type=int, default=0, show_default=True, help="COLMAP's random seed.")
@click.option("--threads", type=int, default=0, show_default=True, help="CPU threads (0: all).")
@click.option("--overwrite", is_flag=True, help="Replace an existing, non-empty --out folder.")
@click.option("--quiet", "-q", is_flag=True, help="No progress display.")
@click.pass_context
def command(ctx, images, out, camera_model, camera_mode, max_image_size, min_registered, seed, threads,
            overwrite, quiet):
    """Estimate camera poses for the photos in IMAGES and write a scene `splatk fit` reads.

    Runs COLMAP's pipeline through pycolmap on the CPU (SIFT features, exhaustive matching,
    incremental mapping), keeps the largest model and undistorts it into SCENE/images and
    SCENE/sparse/0. Exhaustive matching grows with the square of the photo count: fine for
    tens of photos, slow for hundreds.
    """
    verbose = bool(ctx.obj and ctx.obj.get("verbose"))
    console = Console(stderr=True)
    progress = None if quiet else Progress(
        SpinnerColumn(), TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), console=console, transient=False)
    tasks: dict[str, int] = {}

    def on_progress(step: str, done: int, total: int) -> None:
        if progress is None:
            return
        if step not in tasks:
            for other in tasks.values():  # the previous step is over
                progress.update(other, completed=progress.tasks[other].total)
            tasks[step] = progress.add_task(_STEPS.get(step, step), total=total)
        progress.update(tasks[step], completed=done, total=total)

    if progress is not None:
        progress.start()
    try:
        scene = run_sfm(images, out, overwrite=overwrite, camera_model=camera_model, max_image_size=max_image_size,
                        on_progress=on_progress, camera_mode=camera_mode, min_registered=min_registered,
                        seed=seed, threads=threads, verbose=verbose)
    finally:
        if progress is not None:
            progress.stop()
    s = json.loads((scene / "sfm.json").read_text())
    console.print(f"registered {s['registered']}/{s['images']} images, {s['points']:,} points, "
                  f"reprojection error {s['mean_reprojection_error_px']:.2f} px, {s['seconds']['total']:.0f} s")
    if s["not_registered"]:
        console.print(f"[yellow]not registered: {', '.join(s['not_registered'])}")
    console.print(f"wrote {scene}; next: splatk fit {scene} --out RUN")
