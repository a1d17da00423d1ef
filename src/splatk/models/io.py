"""Saving and loading trained models in splatk's native format (a torch file)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

import torch

from ..colors import make_color_model
from ..kernels import make_kernel
from ..torch_files import load_torch_file
from .planar import PlanarModel
from .train_views import TrainViews
from .volumetric import SplatModel

FORMAT_VERSION = 1


def atomic_write(path: str | Path, write: Callable[[BinaryIO], None]) -> Path:
    """Call ``write`` on a temp file in the same folder, fsync, then rename: a crash never leaves
    a half-written file in place of a good one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it owner-only; results are not secrets
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_torch_save(obj, path: str | Path) -> Path:
    """:func:`atomic_write` of ``torch.save(obj)``."""
    return atomic_write(path, lambda f: torch.save(obj, f))


#: kernel options whose default changed: (kernel name, option) -> the value files that do not
#: record it were made with (the learned kernel's profile was unbounded at its support edge, and
#: its interior samples had no envelope)
OPTIONS_BEFORE_RECORDED = {("learned", "edge_max"): 1.0, ("learned", "envelope_power"): 0.0}


def model_spec(model: SplatModel | PlanarModel, kernel_options: dict, color_options: dict) -> dict:
    options = dict(kernel_options)
    for (kernel, name), _ in OPTIONS_BEFORE_RECORDED.items():  # recorded, so a later default cannot change it
        if model.kernel.name == kernel and hasattr(model.kernel, name):
            options.setdefault(name, getattr(model.kernel, name))
    return {
        "primitive": getattr(model, "primitive", "volumetric"),
        "kernel": model.kernel.name,
        "kernel_options": options,
        "color": model.color.name,
        "color_options": dict(color_options),
    }


def save_model(model: SplatModel, path, spec: dict, meta: dict | None = None,
               train_cameras: list | None = None) -> Path:
    """The model file; ``train_cameras`` (the views it was fitted to) are kept with it, else the
    model's own ``train_views`` where it has them."""
    obj = {
        "format": "splatk-model",
        "version": FORMAT_VERSION,
        "spec": spec,
        "prims": {k: v.detach().cpu() for k, v in model.prims.items()},
        "kernel_state": {k: v.cpu() for k, v in model.kernel.state_dict().items()},
        "meta": meta or {},
    }
    views = TrainViews.of(train_cameras) if train_cameras else getattr(model, "train_views", None)
    if views is not None:
        obj["train_views"] = views.state()
    return atomic_torch_save(obj, path)


def build_model(spec: dict, prims: dict, kernel_state: dict | None = None) -> SplatModel | PlanarModel:
    color = make_color_model(spec["color"], **spec.get("color_options", {}))
    primitive = spec.get("primitive", "volumetric")  # files from before planar models: volumetric
    if primitive == "planar":
        options = dict(spec.get("kernel_options", {}))
        if kernel_state and spec["kernel"] == "learned":
            # the saved networks are loaded below: do not read a weights file that may be gone
            options["weights"] = "none"
        model = PlanarModel(make_kernel(spec["kernel"], "planar", **options), color, prims)
    elif primitive == "volumetric":
        options = dict(spec.get("kernel_options", {}))
        for (kernel, name), before in OPTIONS_BEFORE_RECORDED.items():
            if spec["kernel"] == kernel:
                options.setdefault(name, before)  # a file from before the option: as it was made
        model = SplatModel(make_kernel(spec["kernel"], **options), color, prims)
    else:
        raise ValueError(f"unknown primitive type {primitive!r} in model spec")
    kernel = model.kernel
    if kernel_state:
        kernel.load_state_dict(kernel_state)
    return model


def load_model(path) -> tuple[SplatModel, dict]:
    from ..errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "model file not found", "run `splatk fit` first")
    try:
        obj = load_torch_file(path, "re-run `splatk fit`")
    except InputError:
        raise
    except Exception as e:  # corrupt / truncated
        raise InputError(path, f"cannot read model ({type(e).__name__})", "re-run `splatk fit`") from e
    if not isinstance(obj, dict) or obj.get("format") != "splatk-model":
        raise InputError(path, "not a splatk model file")
    try:
        model = build_model(obj["spec"], obj["prims"], obj.get("kernel_state"))
        if obj.get("train_views") is not None and isinstance(model, SplatModel):
            model.train_views = TrainViews.from_state(obj["train_views"])
        meta = {"spec": obj["spec"], **obj.get("meta", {})}
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as e:  # hand-edited, other version
        detail = (str(e).strip().splitlines() or [""])[0][:120]
        raise InputError(path, f"model file is incomplete or inconsistent ({type(e).__name__}: {detail})",
                         "re-run `splatk fit`") from None
    return model, meta
