"""The near clip plane: a primitive nearer to the camera than the model's near plane is not drawn,
in every backend and for both primitive types; fit sets the plane from the scene's size and the
model file keeps it."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scenes import synthetic_scene  # noqa: E402
from splatk import backends
from splatk.data.types import Camera
from splatk.models.base import NEAR_PLANE_BEFORE_RECORDED, NEAR_PLANE_OF_EXTENT
from splatk.models.io import load_model, model_spec, save_model
from splatk.models.planar import PlanarModel
from splatk.models.volumetric import SplatModel
from splatk.stages.fit import build_model
from splatk.stages.fit_config import FitConfig

SIZE = 32
CAMERA = Camera("near.png", SIZE, SIZE, 20.0, 20.0, SIZE / 2, SIZE / 2, torch.eye(4))


def cpu_backends() -> list[str]:
    return [name for name in backends.backend_names() if backends.is_available(name, "cpu")]


def one_primitive(model_class, depth: float, near_plane: float):
    """One opaque primitive on the optical axis at camera depth ``depth`` (the camera is the
    world frame), facing it, small enough that its whole support is in the image."""
    kernel = "gaussian"
    model = model_class.from_points(torch.tensor([[0.0, 0.0, depth]]), torch.tensor([[0.9, 0.5, 0.1]]),
                                    kernel=kernel, color="sh", color_options={"sh_degree": 0},
                                    near_plane=near_plane)
    with torch.no_grad():
        model.prims["log_scales"].fill_(math.log(0.05 * depth))
        model.prims["opacity_logits"].fill_(4.0)
        model.prims["quats"].copy_(torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    return model


@pytest.mark.parametrize("model_class", [SplatModel, PlanarModel], ids=["volumetric", "planar"])
@pytest.mark.parametrize("backend", cpu_backends())
def test_a_primitive_nearer_than_the_near_plane_is_not_drawn(model_class, backend):
    renderer = backends.get(backend)
    for near_plane, drawn in [(0.1, True), (0.3, False)]:
        model = one_primitive(model_class, 0.2, near_plane)
        with torch.no_grad():
            out = model.render(CAMERA, torch.zeros(3), sh_degree=0, backend=renderer)
        covered = float(out.alpha.max())
        if drawn:
            assert covered > 0.5, (near_plane, covered)
            assert out.visible.numel() == 1
        else:
            assert covered == 0.0, (near_plane, covered)
            assert out.visible.numel() == 0


def test_fit_sets_the_near_plane_from_the_scene_and_the_model_file_keeps_it(tmp_path):
    scene = synthetic_scene()
    cfg = FitConfig(kernel="gaussian", sh_degree=1)
    model = build_model(scene, cfg)
    assert model.near_plane == pytest.approx(NEAR_PLANE_OF_EXTENT * scene.extent)
    spec = model_spec(model, cfg.kernel_options, {"sh_degree": 1})
    loaded, meta = load_model(save_model(model, tmp_path / "model.pt", spec))
    assert loaded.near_plane == pytest.approx(model.near_plane)
    assert meta["spec"]["near_plane"] == pytest.approx(model.near_plane)
    # a file written before the near plane was recorded draws as it was made
    del spec["near_plane"]
    old, _ = load_model(save_model(model, tmp_path / "old.pt", spec))
    assert old.near_plane == NEAR_PLANE_BEFORE_RECORDED
