"""``backends.get``: names and ``auto`` resolve to Backend objects, each backend's ops agree with
the torch backend's on the same inputs, and the trainer resolves its backend once."""
import sys
from pathlib import Path

import pytest
import torch

from splatk import backends
from splatk.backends import Backend, PlanarProfile, Profile
from splatk.errors import BackendUnavailable

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

needs_cpu = pytest.mark.skipif(not backends.is_available("cpu"), reason="native cpu backend unavailable")


def test_names_resolve_to_backend_objects():
    torch_backend = backends.get("torch")
    assert isinstance(torch_backend, Backend) and torch_backend.name == "torch"
    assert torch_backend.device == torch.device("cpu")
    assert set(backends.backend_names()) >= {"torch", "cpu"}
    auto = backends.get("auto", "cpu")
    assert auto.name == ("cpu" if backends.is_available("cpu") else "torch")
    assert backends.get("auto", "meta").name == "torch"  # the native backend runs CPU tensors only
    with pytest.raises(ValueError, match="unknown backend 'nope'.*torch"):
        backends.get("nope")


def test_a_backend_that_cannot_run_on_the_device_says_why():
    with pytest.raises(BackendUnavailable, match="'cpu'.*CPU tensors only.*--backend torch"):
        backends.get("cpu", "meta")
    assert not backends.is_available("cpu", "meta")


def test_optional_native_ops_are_absent_from_the_torch_backend():
    b = backends.get("torch")
    assert b.render_image_splats is None
    args = (None, torch.rand(3, 3), torch.rand(3, 3), torch.eye(3).expand(3, 3, 3), True, True, True, 2.5, 5.0, 2.5)
    with torch.no_grad():
        assert b.learned_encode(*args) is None


@needs_cpu
def test_cpu_learned_ops_answer_none_while_autograd_records():
    b = backends.get("cpu")
    args = (None, torch.rand(3, 3) + 1, torch.rand(3, 3), torch.eye(3).expand(3, 3, 3).contiguous(),
            True, True, True, 2.5, 5.0, 2.5)
    assert b.learned_encode(*args) is None
    with torch.no_grad():
        assert b.learned_encode(*args).shape == (3, 4 + 3 + 9)


def _inputs(dtype=torch.float64):
    g = torch.Generator().manual_seed(0)
    n = 40
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.6 + torch.tensor([0, 0, 4.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.05
    vm = torch.eye(4, dtype=dtype)
    K = torch.tensor([[60.0, 0, 24], [0, 60.0, 20], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, vm, K


@needs_cpu
@pytest.mark.parametrize("op", ["project", "sh_colors", "ssim", "rasterize", "rasterize_planar"])
def test_every_op_of_the_cpu_backend_agrees_with_torch(op):
    """The same call on both objects: values and the gradient of a fixed weighted sum."""
    means, quats, scales, vm, K = _inputs()
    w, h = 48, 40

    def run(backend: Backend):
        leaves = [t.clone().requires_grad_() for t in (means, quats, scales)]
        m, q, s = leaves
        if op == "project":
            p = backend.project(m, q, s, vm, K, w, h, support_sigmas=3.0, want_view=True)
            out = torch.cat([p.means2d.flatten(), p.conics.flatten(), p.means_cam.flatten()])
        elif op == "sh_colors":
            sh0 = torch.randn(len(m), 1, 3, generator=torch.Generator().manual_seed(2), dtype=m.dtype)
            rest = torch.randn(len(m), 15, 3, generator=torch.Generator().manual_seed(3), dtype=m.dtype)
            out = backend.sh_colors(sh0, rest, m, 3).flatten()  # m as the view directions
        elif op == "ssim":
            img = torch.sigmoid(m.reshape(8, 5, 3) * 3)  # 40 means: an 8 x 5 RGB image
            ref = torch.rand(8, 5, 3, generator=torch.Generator().manual_seed(4), dtype=m.dtype)
            out = backend.ssim(img, ref).reshape(1)
        elif op == "rasterize":
            p = backends.get("torch").project(m, q, s, vm, K, w, h)
            opac = torch.full((len(m),), 0.7, dtype=m.dtype)
            cols = torch.sigmoid(m)
            out = backend.rasterize(p.means2d, p.conics, opac, cols, p.depths.detach(), Profile("gaussian"),
                                    w, h, torch.ones(3, dtype=m.dtype)).colors.flatten()
        else:
            opac = torch.full((len(m),), 0.7, dtype=m.dtype)
            out = backend.rasterize_planar(m, q, s[:, :2], opac, torch.sigmoid(m), vm, K, w, h,
                                           PlanarProfile("gaussian_surfel"), torch.ones(3, dtype=m.dtype)).colors.flatten()
        weights = torch.linspace(-1, 1, out.numel(), dtype=out.dtype)
        grads = torch.autograd.grad((out * weights).sum(), leaves, allow_unused=True)
        return out.detach(), grads

    out_c, grads_c = run(backends.get("cpu"))
    out_t, grads_t = run(backends.get("torch"))
    torch.testing.assert_close(out_c, out_t, rtol=1e-9, atol=1e-9)
    assert any(gt is not None and gt.abs().max() > 0 for gt in grads_t), "the test passes no gradient"
    for gc, gt in zip(grads_c, grads_t):
        if gt is not None:
            torch.testing.assert_close(gc, gt, rtol=1e-7, atol=1e-9 * max(1.0, float(gt.abs().max())))


def test_the_trainer_resolves_its_backend_once(monkeypatch):
    from splatk.models.volumetric import SplatModel
    from splatk.train.trainer import TrainConfig, Trainer

    scene = synthetic_scene(num_views=3, size=24)
    model = SplatModel.from_points(scene.points, scene.point_colors, color_options={"sh_degree": 1})
    calls = []
    real_get = backends.get
    monkeypatch.setattr(backends, "get", lambda *a, **k: calls.append(a) or real_get(*a, **k))
    trainer = Trainer(scene, model, TrainConfig(iters=4, budget=60, backend="torch"))
    for _ in range(4):
        trainer.train_step()
    assert calls == [("torch", torch.device("cpu"))]
    assert trainer.backend.name == "torch"
