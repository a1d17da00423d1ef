"""Decision 0121: a drawn view gives Φ_proj a primitive's distance as no nearer than the nearest
train camera that draws it; train views draw as without the hold; the model file keeps its cameras."""
from __future__ import annotations

import pytest
import torch

from splatk import backends
from splatk.models.io import load_model, model_spec, save_model
from splatk.models.train_views import TrainViews, nearest_drawing_distance
from tests.scenes import look_at, orbit_cameras, random_model

BACKGROUND = torch.zeros(3)


def learned_model(seed: int = 1):
    model = random_model(80, seed=seed, kernel="learned")
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():  # latents away from zero: profiles that differ with the distance
        model.prims["z3d"].data[:] = 2.0 * torch.randn(model.prims["z3d"].shape, generator=g)
    return model


def near_camera(template):
    """A camera at radius 1 looking at the scene: far nearer to its primitives than the orbit's 4."""
    cam = orbit_cameras(1)[0]
    cam.world_to_cam = look_at((1.0, 0.2, 0.3))
    cam.name = "near.png"
    return cam


def available(name: str):
    if not backends.is_available(name):  # the native backend needs a compiler
        pytest.skip(f"{name} backend unavailable")
    return backends.get(name, "cpu")


@pytest.mark.parametrize("backend_name", ["torch", "cpu"])
@torch.no_grad()
def test_train_views_draw_as_without_the_hold(backend_name):
    backend = available(backend_name)
    model = learned_model()
    cams = orbit_cameras(6)
    before = [model.render(c, BACKGROUND, backend=backend).image for c in cams]
    model.train_views = TrainViews.of(cams)
    for cam, image in zip(cams, before):
        torch.testing.assert_close(model.render(cam, BACKGROUND, backend=backend).image, image, atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend_name", ["torch", "cpu"])
@torch.no_grad()
def test_a_nearer_view_reads_the_nearest_train_distance(backend_name):
    """Φ_proj sees each drawn primitive at max(its distance, the nearest train camera's that draws
    it), along the same ray; the image changes where the hold binds."""
    backend = available(backend_name)
    model = learned_model()
    cams = orbit_cameras(6)
    test = near_camera(cams[0])
    free = model.render(test, BACKGROUND, backend=backend).image
    model.train_views = TrainViews.of(cams)
    seen = {}
    fitted_profile = model.kernel.profile

    def recording_profile(vis, view):
        seen["means_cam"] = view.means_cam.clone()
        return fitted_profile(vis, view)

    model.kernel.profile = recording_profile
    try:
        result = model.render(test, BACKGROUND, backend=backend)
    finally:
        del model.kernel.profile
    proj = backend.project(model.prims["means"], model.prims["quats"], model.scales, test.world_to_cam, test.K,
                           test.width, test.height, support_sigmas=model.kernel.support_sigmas, want_view=True)
    fitted = proj.means_cam.index_select(0, result.visible)
    nearest = nearest_drawing_distance(model.prims["means"], model.prims["quats"], model.scales,
                                       model.train_views, backend, model.kernel.support_sigmas)
    nearest = nearest.index_select(0, result.visible)
    held = seen["means_cam"]
    expected = torch.maximum(fitted.norm(dim=1), nearest)
    torch.testing.assert_close(held.norm(dim=1), expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(torch.nn.functional.normalize(held, dim=1),
                               torch.nn.functional.normalize(fitted, dim=1), rtol=0, atol=1e-6)
    binds = fitted.norm(dim=1) < nearest
    assert binds.sum() >= 5, "the near camera should be nearer than the orbit to several primitives"
    assert (held[~binds] == fitted[~binds]).all()
    assert (result.image - free).abs().max() > 1e-3


@torch.no_grad()
def test_nearest_distance_is_zero_where_no_train_view_draws():
    backend = backends.get("torch", "cpu")
    model = learned_model()
    cams = orbit_cameras(4)
    with torch.no_grad():
        model.prims["means"].data[0] = torch.tensor([40.0, 40.0, 40.0])  # behind or beside every camera
    nearest = nearest_drawing_distance(model.prims["means"], model.prims["quats"], model.scales,
                                       TrainViews.of(cams), backend, model.kernel.support_sigmas)
    assert nearest[0] == 0 and (nearest[1:] > 2.0).sum() > 40


@torch.no_grad()
def test_model_file_keeps_its_train_views(tmp_path):
    backend = backends.get("torch", "cpu")
    model = learned_model()
    cams = orbit_cameras(5)
    spec = model_spec(model, {}, {"sh_degree": 1})
    save_model(model, tmp_path / "held.pt", spec, train_cameras=cams)
    save_model(model, tmp_path / "old.pt", spec)
    held, _ = load_model(tmp_path / "held.pt")
    old, _ = load_model(tmp_path / "old.pt")
    assert old.train_views is None and len(held.train_views) == 5
    torch.testing.assert_close(held.train_views.world_to_cam, torch.stack([c.world_to_cam for c in cams]))
    test = near_camera(cams[0])
    model.train_views = TrainViews.of(cams)
    torch.testing.assert_close(held.render(test, BACKGROUND, backend=backend).image,
                               model.render(test, BACKGROUND, backend=backend).image)
    model.train_views = None
    torch.testing.assert_close(old.render(test, BACKGROUND, backend=backend).image,
                               model.render(test, BACKGROUND, backend=backend).image)


def test_fit_keeps_the_views_it_was_fitted_to(tmp_path):
    """`splatk fit`'s model.pt holds its train cameras (the scene's train split, as fitted)."""
    from splatk.data import load_scene
    from splatk.data.synthetic import make_demo_scene
    from splatk.stages.fit import FitConfig, run_fit
    from splatk.train.trainer import TrainConfig

    scene_path = make_demo_scene(tmp_path / "scene", num_views=8, size=24)
    cfg = FitConfig(sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=5, budget=100, init="random", backend="torch"))
    run = run_fit(scene_path, tmp_path / "run", cfg).path
    model, _ = load_model(run / "model.pt")
    train = load_scene(scene_path).train
    assert len(model.train_views) == len(train) > 0
    torch.testing.assert_close(model.train_views.world_to_cam, torch.stack([c.world_to_cam for c in train]))
    assert model.train_views.sizes.tolist() == [[c.width, c.height] for c in train]
