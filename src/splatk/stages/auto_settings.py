"""The ``auto`` settings a fit resolves from its scene (``init``, ``k``), and the settings of a
run as its ``config.yaml`` records them, found before anything trains."""
from __future__ import annotations

from ..data import load_scene
from ..errors import InputError
from ..kernels.auto_k import AUTO_K, resolve_auto_k
from .fit_config import FitConfig


def train_pixels_per_view(train_views: list) -> float:
    """The mean pixel count of the train views: what ``k: auto`` reads (decision 0102)."""
    return sum(v.width * v.height for v in train_views) / len(train_views)


def settings_as_run(scene_path, cfg: FitConfig) -> FitConfig:
    """A copy of ``cfg`` as a new fit of ``scene_path`` records it in ``config.yaml``: with
    ``init: auto`` and ``k: auto`` resolved from the scene. Reads the cameras and points, not the
    images, so that a caller can tell a run folder's settings from the ones asked for before
    anything trains (`splatk bench` resumes a stopped cell, and runs a cell once when two
    methods come out the same)."""
    resolved = FitConfig.from_dict(cfg.to_dict())
    if resolved.train.init != "auto" and resolved.kernel_options.get("k") != AUTO_K:
        return resolved
    scene = load_scene(scene_path, downscale=cfg.downscale, test_every=cfg.test_every, load_images=False,
                       eval_split=cfg.eval_split)
    train = scene.train[::cfg.view_stride]
    if not train:
        raise InputError(scene_path, "no training images found")
    resolve_init(resolved, scene)
    resolve_auto_k(resolved.kernel_options, train_pixels_per_view(train), resolved.train.budget)
    return resolved


def resolve_init(cfg: FitConfig, scene) -> None:
    """``init: auto`` becomes ``sfm`` where the scene has points, else ``random``; recorded
    resolved, so config.yaml says what ran."""
    if cfg.train.init == "auto":
        cfg.train.init = "sfm" if scene.points.shape[0] > 0 else "random"
