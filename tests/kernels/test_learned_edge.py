"""The learned kernel's profile falls towards its support edge, so the geometry keeps its gradients
(docs/decisions/0101-learned-kernel-unfreeze.md)."""
import pytest
import torch

from splatk import backends
from splatk.kernels.learned import EDGE_MAX, LearnedKernel
from tests.kernels.test_learned_kernel import view_of
from tests.scenes import orbit_cameras, random_model


def box_model(edge_max: float, n: int = 40, seed: int = 6):
    """A learned-kernel model whose Phi_dec outputs 1 at every radius (a flat box: what the
    networks drift to when the edge is not bounded)."""
    model = random_model(n, seed, kernel="learned")
    model.kernel.edge_max = edge_max
    model.kernel.sample_bound[-1] = edge_max
    with torch.no_grad():
        model.kernel.dec[-1].bias.fill_(30.0)  # sigmoid(30) = 1 in float32
    return model


def scale_grad(model) -> float:
    cam = orbit_cameras(4)[1]
    out = model.render(cam, torch.ones(3), sh_degree=1, backend=backends.get("torch", "cpu"))
    g = torch.Generator().manual_seed(0)
    (out.image * torch.rand(out.image.shape, generator=g)).sum().backward()
    return float(model.prims["log_scales"].grad.abs().sum())


def test_the_edge_sample_is_bounded_on_every_path():
    model = box_model(EDGE_MAX)
    cam = orbit_cameras(3)[0]
    view = view_of(model, cam)
    table = model.kernel.profile(dict(model.prims), view).params  # torch path, with gradients
    assert table[:, 0].min() > 0.99 and (table[:, -1] - EDGE_MAX).abs().max() < 1e-6
    view.backend = backends.get("cpu", "cpu")  # the native ops
    with torch.no_grad():  # the native paths (eval, export) draw the same table
        fused = model.kernel.profile(dict(model.prims), view).params
    assert (fused[:, -1] <= EDGE_MAX + 1e-3).all() and (fused[:, 0] > 0.99).all()
    assert model.kernel.gaussian_scale_factor(dict(model.prims)).max() < 0.6  # the bound is exported too


def test_a_flat_profile_leaves_the_scales_without_gradient_and_the_bound_restores_it():
    # The rasteriser does not differentiate the support's cut-off edge: a primitive's scales get
    # their gradient from the profile's slope inside it, which a flat box does not have.
    flat = scale_grad(box_model(1.0))
    bounded = scale_grad(box_model(EDGE_MAX))
    assert bounded > 1e-3
    assert flat < 1e-4 * bounded, (flat, bounded)


def test_edge_max_is_an_option_and_is_checked():
    kern = LearnedKernel(k=4, edge_max=0.5)
    assert kern.options["edge_max"] == 0.5
    assert kern.sample_bound.tolist() == [1.0, 1.0, 1.0, 0.5]
    assert LearnedKernel().options["edge_max"] == EDGE_MAX
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="edge_max"):
            LearnedKernel(edge_max=bad)


def test_models_saved_before_the_bound_render_as_they_were_made(tmp_path):
    from splatk.models.io import build_model, model_spec

    model = box_model(EDGE_MAX)
    spec = model_spec(model, {}, {"sh_degree": 1})
    assert spec["kernel_options"]["edge_max"] == EDGE_MAX  # recorded in every new file
    prims = {k: v.detach() for k, v in model.prims.items()}
    assert build_model(spec, prims, model.kernel.state_dict()).kernel.edge_max == EDGE_MAX
    assert spec["kernel_options"]["envelope_power"] == model.kernel.envelope_power > 0
    old = {**spec, "kernel_options": {}}  # a file written before edge_max and the envelope existed
    rebuilt = build_model(old, prims, model.kernel.state_dict()).kernel
    assert rebuilt.edge_max == 1.0 and rebuilt.envelope_power == 0.0


def test_the_envelope_keeps_a_k8_box_falling_on_every_path_and_leaves_the_pretrained_cosine():
    """k > 2: each interior sample is at most d(0) (1 - (1 - edge_max) r^p)
    (docs/decisions/0104-learned-kernel-profile-envelope.md)."""
    model = random_model(40, 6, kernel="learned")
    cam = orbit_cameras(3)[0]
    kern = LearnedKernel(k=8)
    r = torch.linspace(0, 1, 8)
    envelope = 1 - (1 - EDGE_MAX) * r ** kern.envelope_power
    # the shipped networks at z3d = 0 (cosine in r^2) lie under the envelope: (nearly) unchanged
    cosine = torch.cos(torch.pi / 2 * r ** 2)
    assert (cosine[1:-1] <= envelope[1:-1]).all()
    view = view_of(model, cam)
    z2d = kern.project(torch.zeros(len(view.scales), kern.latent_dim), view)
    raw = kern.decode(z2d, kern.radii2)
    drawn = kern.samples(z2d)
    assert torch.allclose(drawn[:, :-1], raw[:, :-1], atol=1e-3)  # within 1e-3 of what it drew
    # a box from Phi_dec is held under the envelope, on the torch and the native paths
    box = LearnedKernel(k=8)
    with torch.no_grad():
        box.dec[-1].bias.fill_(30.0)
    model.kernel = box
    with torch.no_grad():
        model.prims["z3d"] = torch.nn.Parameter(torch.zeros(model.num_primitives, box.latent_dim))
    view = view_of(model, cam)
    table = box.profile(dict(model.prims), view).params
    assert torch.allclose(table[:, 1:-1], envelope[1:-1].expand_as(table[:, 1:-1]), atol=1e-5)
    view.backend = backends.get("cpu", "cpu")
    with torch.no_grad():
        native = box.profile(dict(model.prims), view).params
    assert (native[:, 1:-1] <= envelope[1:-1] + 1e-3).all()
    # off: the box is drawn as Phi_dec gives it
    assert LearnedKernel(k=8, envelope_power=0).bound(torch.ones(2, 8))[:, 1:-1].eq(1).all()
    # k = 2 has no interior samples: the envelope does not apply
    assert LearnedKernel(k=2).bound(torch.ones(1, 2)).tolist() == [[1.0, EDGE_MAX]]
