"""`splatk sfm IMAGES --out SCENE`: unposed photos -> a COLMAP scene that `splatk fit` reads.

COLMAP's pipeline through pycolmap, on the CPU: SIFT feature extraction, exhaustive matching,
incremental mapping; the model with the most registered images is kept and undistorted to
pinhole cameras (``pycolmap.undistort_images``)::

    SCENE/images/     undistorted images, named as in IMAGES (only the registered ones)
    SCENE/sparse/0/   cameras.bin (PINHOLE), images.bin, points3D.bin (+ pycolmap's rigs/frames)
    SCENE/sfm.json    summary: images in / registered / left out, points, reprojection error,
                      settings, seconds per step

The work files (feature database, distorted models) live in a temporary folder beside SCENE,
and SCENE is put in place only when every step succeeded, so a failed run never costs an
existing scene (hloc's and COLMAP's automatic reconstructor write into the target as they go).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import pycolmap

from ..data._common import check_image_file, image_size
from ..errors import InputError
from ..outputs import check_output_dir, write_marker

#: the marker kind of a scene folder `splatk sfm` wrote (``splatk.outputs``)
SFM_KIND = "sfm scene"

#: file suffixes taken as photos (compared in lower case); other files in IMAGES are ignored
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
#: how cameras are shared between images (pycolmap.CameraMode)
CAMERA_MODES = {"auto": "AUTO", "single": "SINGLE", "per-image": "PER_IMAGE"}
#: SfM needs at least this many photos (two for the initial pair, one to register against it)
MIN_IMAGES = 3


def list_images(images_dir: Path) -> list[Path]:
    """The photos directly in ``images_dir`` (not in sub-folders), sorted by name."""
    return sorted(p for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def check_inputs(images_dir: Path, out_dir: Path, overwrite: bool, camera_model: str,
                 camera_mode: str) -> list[Path]:
    """Every input checked before any work: photos present, readable and enough of them; the
    output folder free (or ``overwrite``), writable and not holding the photos; settings valid.
    Returns the photos."""
    if not images_dir.exists():
        raise InputError(images_dir, "image folder does not exist", "check the path")
    if not images_dir.is_dir():
        raise InputError(images_dir, "is not a folder", "pass the folder that holds the photos")
    images = list_images(images_dir)
    if not images:
        raise InputError(images_dir, f"contains no images ({', '.join(IMAGE_SUFFIXES)})",
                         "put the photos directly in this folder (sub-folders are not searched)")
    if len(images) < MIN_IMAGES:
        raise InputError(images_dir, f"has only {len(images)} image(s); SfM needs at least {MIN_IMAGES}",
                         "add more photos of the scene, from different viewpoints that overlap")
    for path in images:
        check_image_file(path, images_dir.name)
        image_size(path)  # header decodes (a corrupt file names itself here, not in COLMAP's log)
    models = [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]
    if camera_model not in models:
        raise InputError(None, f"unknown camera model {camera_model!r}",
                         "use e.g. SIMPLE_RADIAL (default), OPENCV or PINHOLE")
    if camera_mode not in CAMERA_MODES:
        raise InputError(None, f"unknown camera mode {camera_mode!r}", f"use one of {', '.join(CAMERA_MODES)}")

    out = out_dir.resolve()
    src = images_dir.resolve()
    if out == src or out in src.parents:
        raise InputError(out_dir, "output folder would contain or replace the input photos",
                         "choose an --out outside the image folder (the scene gets its own images/)")
    check_output_dir(out_dir, SFM_KIND, overwrite, inputs=[images_dir])
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise InputError(out_dir, f"cannot write output folder ({e.strerror or e})", "choose a writable --out") from None
    return images


@contextmanager
def _colmap_log(verbose: bool) -> Iterator[None]:
    """COLMAP logs every step to stderr through glog; keep errors only unless ``verbose``."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = old if verbose else max(old, 2)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def run_sfm(
    images_dir: str | Path,
    out_dir: str | Path,
    overwrite: bool = False,
    camera_model: str = "SIMPLE_RADIAL",
    max_image_size: int = 1600,
    on_progress: Callable[[str, int, int], None] | None = None,
    camera_mode: str = "auto",
    min_registered: int = MIN_IMAGES,
    seed: int = 0,
    threads: int = 0,
    verbose: bool = False,
) -> Path:
    """Estimate poses and a sparse point cloud for the photos in ``images_dir``; returns ``out_dir``.

    Args:
        images_dir: folder of photos (jpg, png, tif, bmp; sub-folders are not searched).
        out_dir: scene folder to write (``images/`` + ``sparse/0`` + ``sfm.json``).
        overwrite: replace a non-empty ``out_dir`` (only after the new scene is complete).
        camera_model: COLMAP model estimated per camera (undistorted away at the end).
        max_image_size: longest image side used for SIFT (larger photos are scaled down for
            extraction only; the scene keeps full-size images).
        on_progress: ``(step, done, total)`` with step in features, matching, mapping
            (done = images registered so far), undistortion.
        camera_mode: auto (images of the same size and EXIF share a camera), single (one camera
            for all, e.g. video frames) or per-image (e.g. internet photos).
        min_registered: fewer registered images than this is a failure.
        seed: COLMAP's random seed (RANSAC, mapping); results can still vary a little between
            machines and thread counts.
        threads: CPU threads (0: all cores).
        verbose: show COLMAP's own log.

    Raises:
        InputError: bad input folder, too few photos, or a reconstruction that failed or
            registered fewer than ``min_registered`` images (the message says how many).
    """
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    images = check_inputs(images_dir, out_dir, overwrite, camera_model, camera_mode)
    names = [p.name for p in images]
    n = len(names)
    nthreads = threads if threads and threads > 0 else -1
    progress = on_progress or (lambda step, done, total: None)
    seconds: dict[str, float] = {}
    t_start = time.perf_counter()

    out_dir.resolve().parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.resolve().name}.sfm-", dir=out_dir.resolve().parent))
    try:
        with _colmap_log(verbose):
            pycolmap.set_random_seed(seed)
            db = work / "database.db"

            t = time.perf_counter()
            progress("features", 0, n)
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = camera_model
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.max_image_size = int(max_image_size)
            extraction.num_threads = nthreads
            extraction.use_gpu = False
            pycolmap.extract_features(db, images_dir, image_names=names,
                                      camera_mode=getattr(pycolmap.CameraMode, CAMERA_MODES[camera_mode]),
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            progress("features", n, n)
            seconds["features"] = time.perf_counter() - t

            t = time.perf_counter()
            pairs = n * (n - 1) // 2
            progress("matching", 0, pairs)
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = nthreads
            matching.use_gpu = False
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
            progress("matching", pairs, pairs)
            seconds["matching"] = time.perf_counter() - t
            database = pycolmap.Database.open(str(db))
            try:
                verified_pairs = int(database.num_verified_image_pairs())
                keypoints = {im.name: int(database.num_keypoints_for_image(im.image_id))
                             for im in database.read_all_images()}
            finally:
                database.close()

            t = time.perf_counter()
            registered = {"n": 0}

            def next_image() -> None:
                registered["n"] += 1
                progress("mapping", min(registered["n"], n), n)

            progress("mapping", 0, n)
            mapping = pycolmap.IncrementalPipelineOptions()
            mapping.num_threads = nthreads
            mapping.random_seed = seed
            mapping.min_model_size = max(2, min(int(min_registered), n))  # small photo sets
            (work / "sparse").mkdir()
            models = pycolmap.incremental_mapping(db, images_dir, work / "sparse", options=mapping,
                                                  next_image_callback=next_image)
            seconds["mapping"] = time.perf_counter() - t
            if not models:
                raise InputError(images_dir, f"SfM failed: no reconstruction from {n} images "
                                 f"({verified_pairs} of {pairs} image pairs matched)",
                                 "use more photos of one scene with more overlap and texture"
                                 + ("; try --camera-mode single if one camera took them" if camera_mode != "single" else ""))
            best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
            k = best.num_reg_images()
            progress("mapping", k, n)
            if k < min_registered:
                raise InputError(images_dir, f"SfM registered only {k} of {n} images "
                                 f"(at least {min_registered} needed; {verified_pairs} of {pairs} pairs matched)",
                                 "add photos that overlap more with the others, or remove unrelated ones")

            t = time.perf_counter()
            progress("undistortion", 0, 1)
            model_dir = work / "model"
            model_dir.mkdir()
            best.write(str(model_dir))
            und = work / "undistorted"
            pycolmap.undistort_images(und, model_dir, images_dir, output_type="COLMAP",
                                      num_threads=nthreads)
            progress("undistortion", 1, 1)
            seconds["undistortion"] = time.perf_counter() - t

        scene = work / "scene"
        (scene / "sparse").mkdir(parents=True)
        (und / "images").rename(scene / "images")
        (und / "sparse").rename(scene / "sparse" / "0")
        reg_names = sorted(im.name for im in best.images.values() if im.has_pose)
        seconds["total"] = time.perf_counter() - t_start
        summary = {
            "images": n,
            "registered": k,
            "not_registered": sorted(set(names) - set(reg_names)),
            "points": int(best.num_points3D()),
            "mean_reprojection_error_px": float(best.compute_mean_reprojection_error()),
            "mean_track_length": float(best.compute_mean_track_length()),
            "cameras": int(best.num_cameras()),
            "models_found": [m.num_reg_images() for m in models.values()],
            "verified_pairs": verified_pairs,
            "keypoints": keypoints,
            "settings": {"camera_model": camera_model, "camera_mode": camera_mode,
                         "max_image_size": int(max_image_size), "min_registered": int(min_registered),
                         "seed": seed, "threads": threads},
            "source": str(images_dir.resolve()),
            "pycolmap": getattr(pycolmap, "__version__", "unknown"),
            "seconds": {k_: round(v, 2) for k_, v in seconds.items()},
        }
        (scene / "sfm.json").write_text(json.dumps(summary, indent=2) + "\n")
        write_marker(scene, SFM_KIND)
        _put_in_place(scene, out_dir, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out_dir


def _put_in_place(scene: Path, out_dir: Path, work: Path) -> None:
    """Move the finished ``scene`` to ``out_dir``; an existing one goes only after that worked."""
    old = None
    if out_dir.exists():
        old = work / "previous"
        os.replace(out_dir, old)
    try:
        os.replace(scene, out_dir)
    except OSError:
        if old is not None:
            os.replace(old, out_dir)
        raise
