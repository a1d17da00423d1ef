"""`splatk export`: files other tools open.

* ``ply``: the standard 3DGS PLY (x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*, raw
  pre-activation values) that common viewers read; non-Gaussian kernels are baked to the
  closest Gaussian (scale times the kernel's factor), spherical-Beta lobes are dropped.
* ``native``: the run's model file (everything, networks included), reloadable by splatk.
* ``renders``: test-view PNGs and a GIF along a path through the train cameras.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..models.io import load_model
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
    """Named float32 columns of a 3DGS PLY for ``model``."""
    prims = {k: v.detach().cpu() for k, v in model.prims.items()}
    n = model.num_primitives
    f_dc, f_rest = model.color.base_rgb_params(prims)
    f_rest = f_rest.transpose(1, 2).reshape(n, -1)  # channel-major, as 3DGS writes it
    factor = model.kernel.gaussian_scale_factor(prims)
    if isinstance(factor, torch.Tensor):
        factor = factor.detach().cpu()[:, None]
    log_scales = prims["log_scales"] + torch.log(torch.as_tensor(factor, dtype=torch.float32))
    quats = torch.nn.functional.normalize(prims["quats"], dim=-1)
    cols: dict[str, np.ndarray] = {}
    means = prims["means"].numpy()
    for i, a in enumerate("xyz"):
        cols[a] = means[:, i]
    for a in ("nx", "ny", "nz"):
        cols[a] = np.zeros(n, np.float32)
    for i in range(3):
        cols[f"f_dc_{i}"] = f_dc[:, i].numpy()
    for i in range(f_rest.shape[1]):
        cols[f"f_rest_{i}"] = f_rest[:, i].numpy()
    cols["opacity"] = prims["opacity_logits"].numpy()
    for i in range(3):
        cols[f"scale_{i}"] = log_scales[:, i].numpy()
    for i in range(4):
        cols[f"rot_{i}"] = quats[:, i].numpy()
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in cols.items()}


def export_ply(run: str | Path, out: str | Path, overwrite: bool = False) -> Path:
    from plyfile import PlyData, PlyElement

    check_output_file(out, overwrite, inputs=[Path(run) / "model.pt"])
    model, _ = load_model(Path(run) / "model.pt")
    if getattr(model, "primitive", "volumetric") == "planar":
        # a 3DGS PLY has three scales and viewers draw ellipsoids; faking a thin third scale
        # would look like surfels in some viewers and not others, so say so instead
        raise InputError(Path(run) / "model.pt", "PLY export of planar (surfel) models is not supported",
                         "use `splatk export --format native` or `--format renders`")
    cols = ply_arrays(model)
    dtype = [(k, "f4") for k in cols]
    arr = np.empty(model.num_primitives, dtype=dtype)
    for k, v in cols.items():
        arr[k] = v
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(out))
    return out


def export_native(run: str | Path, out: str | Path, overwrite: bool = False) -> Path:
    src = Path(run) / "model.pt"
    check_output_file(out, overwrite, inputs=[src])
    load_model(src)  # validates
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, out)
    return out


def export_renders(run: str | Path, out: str | Path, backend: str = "auto", gif_frames: int = 48,
                   overwrite: bool = False) -> Path:
    """Test-view PNGs plus ``path.gif`` interpolated between train cameras, into a folder that
    is new, empty, or (with ``overwrite``) an earlier renders export."""
    from .. import backends
    from ..data import load_scene

    out = Path(out)
    model, meta = load_model(Path(run) / "model.pt")
    inputs = [Path(run), meta.get("scene")]
    check_output_dir(out, RENDERS_KIND, overwrite, inputs=inputs)
    renderer = backends.get(backend, "cpu")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0),
                       test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
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
