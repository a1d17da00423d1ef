"""The learned kernel's contract: view dependence, gradients, schedules, options, save/load."""
import math

import pytest
import torch

from splatk import backends
from splatk.errors import InputError
from splatk.functional.projection import project_ellipsoids
from splatk.kernels import ViewContext, make_kernel
from splatk.kernels.learned import DEFAULT_WEIGHTS, LearnedKernel
from splatk.models.io import load_model, model_spec, save_model
from splatk.stages.export import ply_arrays
from splatk.train.mcmc import MCMCConfig
from splatk.train.trainer import TrainConfig, Trainer
from tests.scenes import orbit_cameras, random_model, synthetic_scene


def view_of(model, cam):
    proj = project_ellipsoids(model.prims["means"], model.prims["quats"], model.scales,
                              cam.world_to_cam, cam.K, cam.width, cam.height,
                              support_sigmas=model.kernel.support_sigmas)
    return ViewContext(proj.means_cam, model.scales, proj.rotmats_cam)


def test_defaults_follow_the_paper():
    k = make_kernel("learned")
    assert isinstance(k, LearnedKernel)
    assert k.support_sigmas == 1.0 and k.k == 2
    linears = [m for m in k.proj if isinstance(m, torch.nn.Linear)]
    assert len(linears) == 4 and all(m.out_features == 64 for m in linears[:3])
    assert linears[0].in_features == 5 + 4 + 3 + 9 and linears[-1].out_features == 5
    dec = [m for m in k.dec if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in dec] == [(6, 4), (4, 4), (4, 1)]
    # ~10k floats of networks: the shipped file is small
    assert 8_000 < sum(p.numel() for p in k.parameters()) < 12_000
    assert DEFAULT_WEIGHTS.is_file() and DEFAULT_WEIGHTS.stat().st_size < 100_000
    assert k.init_primitive_params(3, torch.device("cpu"))["z3d"].eq(0).all()
    assert set(k.learning_rates()) == {"z3d"}


def test_pretrained_kernel_is_the_cosine_in_every_view():
    model = random_model(40, 1, kernel="learned")
    for cam in orbit_cameras(3):
        with torch.no_grad():
            table = model.kernel.profile(dict(model.prims), view_of(model, cam)).params
        # cos(pi/2 r^2) at r = 0, 1 (shipped file: |d(0) err| ~0.002, |d(1) err| ~0.01)
        assert (table[:, 0] - 1.0).abs().max() < 0.05
        assert table[:, 1].abs().max() < 0.06


def test_profile_depends_on_the_view():
    model = random_model(30, 2, kernel="learned")
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        model.prims["z3d"].data[:] = torch.randn(30, 5, generator=g)
        for p in model.kernel.proj.parameters():  # strengthen the view inputs' say
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    cams = orbit_cameras(4)
    with torch.no_grad():
        t0 = model.kernel.profile(dict(model.prims), view_of(model, cams[0])).params
        t1 = model.kernel.profile(dict(model.prims), view_of(model, cams[1])).params
        t0b = model.kernel.profile(dict(model.prims), view_of(model, cams[0])).params
    assert torch.equal(t0, t0b)  # deterministic
    assert (t0 - t1).abs().max() > 1e-2  # same primitives, two cameras, different kernels
    # ... and the latent matters too: different z3d, same view
    with torch.no_grad():
        model.prims["z3d"].data[:] = 0
        t2 = model.kernel.profile(dict(model.prims), view_of(model, cams[0])).params
    assert (t0 - t2).abs().max() > 1e-2


@pytest.mark.parametrize("k", [2, 4, 8])
def test_profile_shape_and_empty_view(k):
    kern = LearnedKernel(k=k)
    views = ViewContext(torch.tensor([[0.0, 0.0, 2.0]]), torch.full((1, 3), 0.1), torch.eye(3)[None])
    prof = kern.profile({"z3d": torch.zeros(1, 5)}, views)
    assert prof.kind == "table" and prof.params.shape == (1, k)
    assert ((prof.params > 0) & (prof.params < 1)).all()
    empty = ViewContext(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3, 3))
    assert kern.profile({"z3d": torch.zeros(0, 5)}, empty).params.shape == (0, k)


def test_bad_options():
    with pytest.raises(ValueError):
        LearnedKernel(k=1)
    with pytest.raises(ValueError):
        LearnedKernel(proj_inputs="z,omega")
    with pytest.raises(InputError, match="another network shape"):
        LearnedKernel(latent_dim=3)  # the shipped weights are for latent_dim 5
    kern = LearnedKernel(latent_dim=3, weights="none")
    assert kern.net_lr_mult == 10.0  # paper: no pre-training -> LR x 10


def test_proj_inputs_ablation_without_latent():
    kern = LearnedKernel(proj_inputs="mu,s,R", weights="none")
    assert kern.init_primitive_params(4, torch.device("cpu")) == {}
    assert kern.learning_rates() == {}
    view = ViewContext(torch.randn(4, 3) + torch.tensor([0, 0, 5.0]), torch.rand(4, 3) + 0.1,
                       torch.eye(3).expand(4, 3, 3))
    assert kern.profile({}, view).params.shape == (4, 2)
    assert kern.options["proj_inputs"] == "mu,s,R"


def test_gradients_reach_z3d_and_both_networks():
    model = random_model(40, 3, kernel="learned")
    cam = orbit_cameras(4)[1]
    out = model.render(cam, torch.ones(3), sh_degree=1, backend=backends.get("torch"))
    (out.image * torch.rand_like(out.image)).sum().backward()
    assert model.prims["z3d"].grad is not None and model.prims["z3d"].grad[out.visible].abs().sum() > 0
    for name, p in model.kernel.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    # the view inputs carry gradients back to the geometry as well
    assert model.prims["quats"].grad.abs().sum() > 0


def test_network_lr_freezes_then_decays():
    kern = LearnedKernel()
    iters = 30_000
    lr = [kern.network_learning_rate(it, it / iters) for it in range(1, iters + 1)]
    assert all(v == 0.0 for v in lr[:2000])  # frozen for the first 2000 iterations
    assert lr[2000] == pytest.approx(1.6e-4, rel=1e-3)
    assert lr[-1] == pytest.approx(1.6e-6, rel=1e-6)
    assert all(a > b for a, b in zip(lr[2000:-1], lr[2001:]))  # strictly decreasing
    mid = (2001 + iters) // 2
    assert lr[mid - 1] == pytest.approx(1.6e-5, rel=0.01)  # exponential: geometric mean halfway
    assert LearnedKernel(weights="none").network_learning_rate(2001, 2001 / iters) == pytest.approx(1.6e-3, rel=1e-3)


def test_trainer_keeps_networks_frozen_then_trains_them():
    scene = synthetic_scene(num_views=4, size=24, num_points=20)
    model = random_model(20, 4, kernel="learned")
    model.kernel.freeze_iters = 3
    before = {k: v.clone() for k, v in model.kernel.state_dict().items()}
    tr = Trainer(scene, model, TrainConfig(iters=6, budget=20, backend="torch", mcmc=MCMCConfig(refine_start=100)))
    z0 = model.prims["z3d"].detach().clone()
    for _ in range(3):
        tr.train_step()
    assert all(torch.equal(before[k], v) for k, v in tr.model.kernel.state_dict().items())
    assert not torch.equal(z0, tr.model.prims["z3d"].detach())  # the latents train from the start
    for _ in range(3):
        tr.train_step()
    assert any(not torch.equal(before[k], v) for k, v in tr.model.kernel.state_dict().items())


def test_save_load_round_trip(tmp_path):
    model = random_model(25, 5, kernel="learned")
    opts = {"k": 4, "freeze_iters": 10}
    model.kernel = LearnedKernel(**opts)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        model.prims["z3d"].data[:] = torch.randn(25, 5, generator=g)
        for p in model.kernel.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    path = save_model(model, tmp_path / "model.pt", model_spec(model, opts, {"sh_degree": 1}))
    loaded, meta = load_model(path)
    assert meta["spec"]["kernel"] == "learned" and loaded.kernel.k == 4 and loaded.kernel.freeze_iters == 10
    for k, v in model.kernel.state_dict().items():
        assert torch.equal(loaded.kernel.state_dict()[k], v), k
    assert torch.equal(loaded.prims["z3d"], model.prims["z3d"])
    cam = orbit_cameras(3)[0]
    with torch.no_grad():
        a = model.render(cam, torch.ones(3), sh_degree=1, backend=backends.get("torch")).image
        b = loaded.render(cam, torch.ones(3), sh_degree=1, backend=backends.get("torch")).image
    assert torch.equal(a, b)


def test_weights_file_missing(tmp_path):
    # a run trained with weights that are gone since still loads (the networks are in the run) ...
    model = random_model(10, 6, kernel="learned")
    spec = model_spec(model, {"weights": str(tmp_path / "gone.pt")}, {"sh_degree": 1})
    path = save_model(model, tmp_path / "model.pt", spec)
    loaded, _ = load_model(path)
    cam = orbit_cameras(2)[0]
    with torch.no_grad():
        loaded.render(cam, torch.ones(3), sh_degree=1, backend=backends.get("torch"))
    # ... but a new kernel pointed at a missing file says so when first used
    kern = LearnedKernel(weights=tmp_path / "gone.pt")
    view = ViewContext(torch.tensor([[0.0, 0.0, 2.0]]), torch.full((1, 3), 0.1), torch.eye(3)[None])
    with pytest.raises(InputError, match="not found"):
        kern.profile({"z3d": torch.zeros(1, 5)}, view)


def test_gaussian_scale_factor_matches_second_moment():
    model = random_model(50, 7, kernel="learned")
    prims = {k: v.detach() for k, v in model.prims.items()}
    f = model.kernel.gaussian_scale_factor(prims)
    assert f.shape == (50,) and torch.isfinite(f).all()
    # pretrained k = 2 table ~ (1, 0): a cone 1 - r, whose matching Gaussian has
    # f^2 = int (1 - r) r^3 dr / (2 int (1 - r) r dr) = (1/20) / (2/6) = 0.15
    assert f.mean().item() == pytest.approx(math.sqrt(0.15), abs=0.02)
    cols = ply_arrays(model)
    assert torch.allclose(torch.from_numpy(cols["scale_0"]), prims["log_scales"][:, 0] + torch.log(f), atol=1e-5)
