"""`splatk export`: files other tools open.

* ``ply``, ``splat``, ``spz``: Gaussians (``splatk.export_formats``): the standard 3DGS PLY
  that common viewers read, antimatter15's ``.splat`` and Niantic's SPZ that web viewers and
  sharing sites read. Non-Gaussian kernels are baked to the closest Gaussian (scale times the
  kernel's factor), spherical-Beta lobes and SH bands the format lacks are dropped; when that
  changes the model, the test views are rendered from the model and from the file's Gaussians
  and the result reports both PSNRs (:class:`Approximation`).
* ``native``: the run's model file (everything, networks included), reloadable by splatk.
* ``renders``: test-view PNGs and a GIF along a path through the train cameras.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import backends
from .. import export_formats as formats
from ..errors import InputError
from ..metrics import psnr
from ..models.io import atomic_write, load_model
from ..outputs import OutputDir, check_output_dir, check_output_file

#: the marker kind of a renders folder (``splatk.outputs``)
RENDERS_KIND = "renders"


def write_png(path: str | Path, img: torch.Tensor) -> Path:
    """[H, W, 3] float in [0, 1] -> 8-bit PNG."""
    import cv2

    arr = (img.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)):
        raise InputError(path, "could not write image", "check the folder is writable")
    return path


def ply_arrays(model) -> dict[str, np.ndarray]:
    """Named float32 columns of a 3DGS PLY for ``model`` (non-Gaussian kernels baked)."""
    return formats.ply_arrays(formats.gaussians_of(model)[0])


@dataclass
class Approximation:
    """What a Gaussian file loses of a model, and what that costs on the scene's test views.

    ``psnr_model`` is the mean test PSNR of the model as splatk renders it, ``psnr_export`` that
    of the Gaussians the file holds (before the format's quantisation) rendered the same way
    (both None, with ``not_measured`` saying why, when the scene is not there).
    """

    changes: list[str]
    psnr_model: float | None = None
    psnr_export: float | None = None
    num_views: int = 0
    not_measured: str | None = None

    @property
    def psnr_change(self) -> float | None:
        """``psnr_export - psnr_model`` in dB (negative: the file looks worse)."""
        if self.psnr_model is None or self.psnr_export is None:
            return None
        return self.psnr_export - self.psnr_model

    def line(self) -> str:
        what = "; ".join(self.changes)
        if self.psnr_change is None:
            return f"{what}: test PSNR not measured ({self.not_measured})"
        return (f"{what}: test PSNR {self.psnr_model:.2f} -> {self.psnr_export:.2f} dB "
                f"({self.psnr_change:+.2f} dB, {self.num_views} views)")

    def to_dict(self) -> dict:
        return {"changes": list(self.changes), "psnr_model": self.psnr_model, "psnr_export": self.psnr_export,
                "psnr_change": self.psnr_change, "num_views": self.num_views, "not_measured": self.not_measured,
                "message": self.line()}


@dataclass
class ExportResult:
    """What `splatk export` wrote: the path, the format and, for a Gaussian file of a model it
    could not hold exactly, the :class:`Approximation`."""

    path: Path
    format: str
    approximation: Approximation | None = None

    def to_dict(self) -> dict:
        approx = self.approximation.to_dict() if self.approximation else None
        return {"path": str(self.path), "format": self.format, "approximation": approx}


#: Gaussian file formats: name in messages, writer, the highest SH degree the format stores
GAUSSIAN_FORMATS = {
    "ply": ("PLY", formats.write_ply, 3),
    "splat": (".splat", formats.write_splat, 0),
    "spz": ("SPZ", formats.write_spz, 3),
}


def export_gaussians(run: str | Path, out: str | Path, fmt: str, overwrite: bool = False,
                     backend: str = "auto", scene_path: str | Path | None = None) -> ExportResult:
    """Write RUN's model as Gaussians in ``fmt`` (:data:`GAUSSIAN_FORMATS`).

    When the file cannot hold the model exactly (a non-Gaussian kernel, a colour model other
    than SH, SH bands the format drops), the result's :class:`Approximation` holds the test
    PSNR of the model and of the file's Gaussians, both rendered by splatk with ``backend`` on
    the run's scene (``scene_path`` if it moved).
    """
    name, write, max_sh_degree = GAUSSIAN_FORMATS[fmt]
    model_path = Path(run) / "model.pt"
    check_output_file(out, overwrite, inputs=[model_path])
    model, meta = load_model(model_path)
    if getattr(model, "primitive", "volumetric") == "planar":
        # these formats have three scales and viewers draw ellipsoids; faking a thin third scale
        # would look like surfels in some viewers and not others, so say so instead
        raise InputError(model_path, f"{name} export of planar (surfel) models is not supported",
                         "use `splatk export --format native` or `--format renders`")
    gaussians, changes = formats.gaussians_of(model)
    if gaussians.sh_degree > max_sh_degree:
        changes.append(f"SH degree {gaussians.sh_degree} colour reduced to degree {max_sh_degree} "
                       f"({name} stores no higher bands)")
        gaussians = gaussians.with_sh_degree(max_sh_degree)
    if fmt == "spz" and (problem := formats.check_spz_range(gaussians)):
        raise InputError(model_path, problem, "use `splatk export --format ply` or `--format splat`")
    scene = None
    if changes:
        scene, not_found = _measurement_scene(meta, scene_path)
    atomic_write(out, lambda f: write(gaussians, f))
    approx = None
    if changes and scene is None:
        approx = Approximation(changes, not_measured=not_found)
    elif changes:
        renderer = backends.get(backend, "cpu")
        approx = Approximation(changes, _test_psnr(model, scene, renderer),
                               _test_psnr(gaussians.to_model(), scene, renderer), len(scene.test))
    return ExportResult(Path(out), fmt, approx)


def _run_scene(meta: dict, scene_path: str | Path | None = None):
    from ..data import load_scene

    return load_scene(scene_path or meta["scene"], downscale=meta.get("downscale", 1.0),
                      test_every=meta.get("test_every", 8),
                      background=tuple(meta["background"]) if meta.get("background") else None,
                      eval_split=meta.get("eval_split", "held-out"))


def _measurement_scene(meta: dict, scene_path: str | Path | None):
    """(the scene with test views, None) or (None, why not)."""
    path = scene_path or meta.get("scene")
    if not path or not Path(path).exists():
        return None, f"scene folder {path} not found; pass --scene"
    scene = _run_scene(meta, path)
    if not scene.test:
        return None, f"the scene {path} has no test views"
    return scene, None


def _test_psnr(model, scene, renderer) -> float:
    """Mean PSNR over the scene's test views (as `splatk eval` measures it)."""
    bg = torch.tensor(scene.background, dtype=torch.float32)
    values = []
    with torch.no_grad():
        for cam in scene.test:
            img = model.render(cam, bg, backend=renderer).image.clamp(0, 1)
            values.append(float(psnr(img, cam.image_float())))
    return sum(values) / len(values)


def export_native(run: str | Path, out: str | Path, overwrite: bool = False) -> Path:
    src = Path(run) / "model.pt"
    check_output_file(out, overwrite, inputs=[src])
    load_model(src)  # validates
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, out)
    return out


def export_renders(run: str | Path, out: str | Path, backend: str = "auto", gif_frames: int = 48,
                   overwrite: bool = False, scene_path: str | Path | None = None) -> Path:
    """Test-view PNGs plus ``path.gif`` interpolated between train cameras, into a folder that
    is new, empty, or (with ``overwrite``) an earlier renders export."""
    out = Path(out)
    model, meta = load_model(Path(run) / "model.pt")
    inputs = [Path(run), scene_path or meta.get("scene")]
    check_output_dir(out, RENDERS_KIND, overwrite, inputs=inputs)
    renderer = backends.get(backend, "cpu")
    scene = _run_scene(meta, scene_path)
    with OutputDir(out, RENDERS_KIND, overwrite, inputs=inputs):
        _write_renders(model, scene, out, renderer, gif_frames)
    return out


def _write_renders(model, scene, out: Path, renderer, gif_frames: int) -> None:
    from ..render_path import interpolate_cameras

    bg = torch.tensor(scene.background, dtype=torch.float32)
    frames = []
    with torch.no_grad():
        for cam in scene.test:
            write_png(out / f"{Path(cam.name).stem}.png", model.render(cam, bg, backend=renderer).image)
        for cam in interpolate_cameras(scene.train, gif_frames):
            img = model.render(cam, bg, backend=renderer).image.clamp(0, 1)
            frames.append((img.numpy() * 255 + 0.5).astype(np.uint8))
    if frames:
        from PIL import Image

        ims = [Image.fromarray(f) for f in frames]
        ims[0].save(out / "path.gif", save_all=True, append_images=ims[1:], duration=80, loop=0)
