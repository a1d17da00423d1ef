"""Planar (surfel) primitives through the trainer, save / load and `fit`'s model building."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

from splatk import backends
from splatk.errors import InputError
from splatk.models.io import load_model, model_spec, save_model
from splatk.models.planar import PlanarModel
from splatk.stages.fit import FitConfig, build_model
from splatk.train.mcmc import MCMCConfig
from splatk.train.trainer import TrainConfig, Trainer


def mean_test_psnr(model, scene, backend) -> float:
    bg = torch.tensor(scene.background)
    vals = []
    with torch.no_grad():
        for cam in scene.test:
            img = model.render(cam, bg, backend=backends.get(backend)).image.clamp(0, 1)
            vals.append(float(-10 * torch.log10(((img - cam.image_float()) ** 2).mean())))
    return sum(vals) / len(vals)


@pytest.mark.parametrize("kernel", ["gaussian", "learned"])
def test_short_planar_fit_raises_test_psnr_and_round_trips(kernel, tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        scene = synthetic_scene(size=32)
        opts = {"freeze_iters": 100} if kernel == "learned" else {}
        model = PlanarModel.from_points(scene.points, scene.point_colors, kernel=kernel, color="sh",
                                        kernel_options=opts, color_options={"sh_degree": 1})
        cfg = TrainConfig(iters=300, budget=150, backend="auto", mcmc=MCMCConfig(refine_start=100, refine_every=50))
        tr = Trainer(scene, model, cfg)
        before = mean_test_psnr(tr.model, scene, "auto")
        tr.run()
        after = mean_test_psnr(tr.model, scene, "auto")
    finally:
        torch.set_num_threads(threads)
    assert after > before + 5.0, (before, after)
    assert 60 < tr.model.num_primitives <= 150  # MCMC grew the model within the budget
    assert tr.model.prims["log_scales"].shape[1] == 2

    path = save_model(tr.model, tmp_path / "model.pt", model_spec(tr.model, opts, {"sh_degree": 1}))
    loaded, meta = load_model(path)
    assert isinstance(loaded, PlanarModel) and meta["spec"]["primitive"] == "planar"
    bg = torch.tensor(scene.background)
    with torch.no_grad():
        a = tr.model.render(scene.test[0], bg, backend=backends.get("auto")).image
        b = loaded.render(scene.test[0], bg, backend=backends.get("auto")).image
    assert torch.equal(a, b)


def test_planar_render_backends_agree():
    scene = synthetic_scene(num_views=4, size=24)
    torch.manual_seed(1)
    model = PlanarModel.from_points(scene.points, scene.point_colors, kernel="learned",
                                    color_options={"sh_degree": 1})
    bg = torch.tensor(scene.background)
    with torch.no_grad():
        ref = model.render(scene.train[0], bg, backend=backends.get("torch")).image
        nat = model.render(scene.train[0], bg, backend=backends.get("cpu")).image
    torch.testing.assert_close(nat, ref, atol=2e-5, rtol=0)


def test_build_model_planar_and_unknown_pairs():
    scene = synthetic_scene(num_views=4, size=16)
    m = build_model(scene, FitConfig(primitive="planar", kernel="gaussian"))
    assert isinstance(m, PlanarModel)
    with pytest.raises(InputError, match="'beta' has no planar version"):
        build_model(scene, FitConfig(primitive="planar", kernel="beta"))
    with pytest.raises(InputError, match="unknown primitive"):
        build_model(scene, FitConfig(primitive="curved"))
    with pytest.raises(InputError, match="volumetric-only"):
        build_model(scene, FitConfig(primitive="planar", kernel="learned", kernel_options={"k": 4}))


def test_planar_training_state_round_trip():
    """Stop, save the trainer state, continue: same parameters as not stopping (the path of
    `fit --resume`), with MCMC relocation and growth of two-scale primitives on the way."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = synthetic_scene(num_views=8, size=24)

        def fresh():
            torch.manual_seed(0)
            m = PlanarModel.from_points(scene.points, scene.point_colors, kernel="learned",
                                        kernel_options={"freeze_iters": 20}, color_options={"sh_degree": 1})
            return Trainer(scene, m, TrainConfig(iters=60, budget=100, backend="auto", seed=3,
                                                 mcmc=MCMCConfig(refine_start=10, refine_every=20)))

        a = fresh()
        a.run()
        b = fresh()
        b.run(should_stop=lambda: b.it >= 25)
        c = fresh()
        c.load_state_dict(b.state_dict())
        c.run()
    finally:
        torch.set_num_threads(threads)
    assert c.it == a.it == 60 and a.model.num_primitives > 60
    for k in a.model.prims:
        assert torch.allclose(a.model.prims[k], c.model.prims[k], atol=1e-4), k
    for (name, p), q in zip(a.model.kernel.named_parameters(), c.model.kernel.parameters()):
        assert torch.allclose(p, q, atol=1e-5), name
