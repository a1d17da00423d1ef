"""Native planar rasteriser vs the dense torch reference: images and every gradient."""
from __future__ import annotations

import pytest
import torch

from splatk.backends.planar import PlanarProfile, rasterize_planar
from splatk.backends.planar_torch import planar_visible

W, H = 40, 32
# float32 native vs float64 reference: image values are sums of O(10) float32 products; the
# gradients add the float32 rounding of the cross products and divisions of 2DGS Eq. 10.
TOL = {torch.float32: dict(img=2e-5, grad_rtol=2e-3, grad_atol=2e-4), torch.float64: dict(img=1e-12, grad_rtol=1e-9, grad_atol=1e-10)}


def _native_or_skip():
    from splatk.backends.cpu_native import available

    if not available():
        pytest.skip("native cpu backend unavailable")


def random_scene(n: int, seed: int = 0, dtype=torch.float64, grid: int = 0):
    """n disks in front of an identity camera (f = 40 px) with random orientations and sizes."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    means = torch.stack([(r(n) - 0.5) * 3.0, (r(n) - 0.5) * 2.4, 2.5 + 2.0 * r(n)], 1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = 0.05 + 0.2 * r(n, 2)
    opac = 0.2 + 0.75 * r(n)
    colors = r(n, 3)
    viewmat = torch.eye(4, dtype=dtype)
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]], dtype=dtype)
    table = 0.2 + 0.8 * r(n, grid, grid) if grid else None
    return dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors,
                viewmat=viewmat, K=K), table


def _render(scene, table, kind, backend, dtype, bg):
    leaves = {k: v.to(dtype).clone().requires_grad_(k not in ("viewmat", "K")) for k, v in scene.items()}
    tab = None if table is None else table.to(dtype).clone().requires_grad_(True)
    bgl = bg.to(dtype).clone().requires_grad_(True)
    out = rasterize_planar(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                           leaves["colors"], leaves["viewmat"], leaves["K"], W, H,
                           PlanarProfile(kind, tab), background=bgl, backend=backend)
    g = torch.Generator().manual_seed(7)
    v_img = torch.randn(out.colors.shape, generator=g, dtype=torch.float64).to(dtype)
    v_alpha = torch.randn(out.alphas.shape, generator=g, dtype=torch.float64).to(dtype)
    ((out.colors * v_img).sum() + (out.alphas * v_alpha).sum()).backward()
    grads = {k: leaves[k].grad for k in ("means", "quats", "scales", "opacities", "colors")}
    grads["background"] = bgl.grad
    if tab is not None:
        grads["table"] = tab.grad
    return out, grads


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind,grid", [("gaussian_surfel", 0), ("grid", 6)])
@pytest.mark.parametrize("n,seed", [(20, 0), (60, 1)])
def test_native_matches_reference(kind, grid, n, seed, dtype):
    _native_or_skip()
    scene, table = random_scene(n, seed, grid=grid)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ref, ref_g = _render(scene, table, kind, "torch", torch.float64, bg)
    nat, nat_g = _render(scene, table, kind, "cpu", dtype, bg)
    tol = TOL[dtype]
    assert ref.alphas.max() > 0.5  # the scene covers part of the image
    torch.testing.assert_close(nat.colors.double(), ref.colors, atol=tol["img"], rtol=0)
    torch.testing.assert_close(nat.alphas.double(), ref.alphas, atol=tol["img"], rtol=0)
    for name, gref in ref_g.items():
        assert gref.abs().sum() > 0, name
        torch.testing.assert_close(nat_g[name].double(), gref, rtol=tol["grad_rtol"],
                                   atol=tol["grad_atol"] * gref.abs().max().item(), msg=name)


def test_native_gradcheck_float64():
    _native_or_skip()
    scene, table = random_scene(4, seed=3, grid=4)
    w, h = 12, 10
    K = torch.tensor([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]], dtype=torch.float64)
    names = ("means", "quats", "scales", "opacities", "colors")
    for kind, tab in (("gaussian_surfel", None), ("grid", table)):
        inputs = [scene[k].clone().requires_grad_(True) for k in names]
        bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
        extra = [] if tab is None else [tab.clone().requires_grad_(True)]

        def f(means, quats, scales, opac, colors, bg, *tabs):
            out = rasterize_planar(means, quats, scales, opac, colors, scene["viewmat"], K, w, h,
                                   PlanarProfile(kind, tabs[0] if tabs else None), bg, backend="cpu")
            return out.colors, out.alphas

        assert torch.autograd.gradcheck(f, (*inputs, bg, *extra), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_empty_scene_is_background(backend):
    if backend == "cpu":
        _native_or_skip()
    scene, _ = random_scene(0)
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64)
    out = rasterize_planar(*[scene[k] for k in ("means", "quats", "scales", "opacities", "colors",
                                                "viewmat", "K")], W, H,
                           PlanarProfile("gaussian_surfel"), background=bg, backend=backend)
    assert torch.equal(out.colors, bg.expand(H, W, 3))
    assert torch.equal(out.alphas, torch.zeros(H, W, 1, dtype=torch.float64))


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_splat_behind_or_across_camera_is_dropped(backend):
    if backend == "cpu":
        _native_or_skip()
    scene, _ = random_scene(3, seed=5)
    scene["means"] = torch.tensor([[0.0, 0.0, -2.0],   # behind
                                   [0.0, 0.0, 0.3],    # centre in front, disk crosses z = 0
                                   [0.0, 0.0, 3.0]], dtype=torch.float64)
    scene["quats"] = torch.tensor([[1.0, 0, 0, 0], [0.7071, 0.7071, 0, 0], [1.0, 0, 0, 0]],
                                  dtype=torch.float64)
    scene["scales"] = torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.2, 0.2]], dtype=torch.float64)
    order, _ = planar_visible(scene["means"], scene["quats"], scene["scales"], scene["viewmat"], scene["K"])
    assert order.tolist() == [2]
    full = rasterize_planar(**scene, width=W, height=H, profile=PlanarProfile("gaussian_surfel"),
                            backend=backend)
    only = rasterize_planar(**{k: v[2:] if v.shape[0] == 3 and k not in ("viewmat", "K") else v
                               for k, v in scene.items()},
                            width=W, height=H, profile=PlanarProfile("gaussian_surfel"), backend=backend)
    assert torch.isfinite(full.colors).all()
    torch.testing.assert_close(full.colors, only.colors, atol=1e-6, rtol=0)
    assert full.alphas.max() > 0.5


@pytest.mark.parametrize("kind,grid", [("gaussian_surfel", 0), ("grid", 5)])
def test_native_matches_reference_when_pixels_saturate(kind, grid):
    """Stacks of near-opaque disks: pixels end at the T < 1e-4 stop in both backends."""
    _native_or_skip()
    scene, table = random_scene(60, seed=4, grid=grid)
    scene["means"][:, :2] *= 0.2  # all in the middle of the image
    scene["scales"] = scene["scales"] * 2.0
    scene["opacities"] = torch.full_like(scene["opacities"], 0.98)
    if table is not None:
        table = table.clamp_min(0.9)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ref, ref_g = _render(scene, table, kind, "torch", torch.float64, bg)
    nat, nat_g = _render(scene, table, kind, "cpu", torch.float32, bg)
    assert (ref.alphas > 1 - 1.5e-4).sum() > 20  # the stop is reached
    tol = TOL[torch.float32]
    torch.testing.assert_close(nat.colors.double(), ref.colors, atol=tol["img"], rtol=0)
    for name, gref in ref_g.items():
        torch.testing.assert_close(nat_g[name].double(), gref, rtol=tol["grad_rtol"],
                                   atol=tol["grad_atol"] * gref.abs().max().item(), msg=name)


def test_bboxes_hold_the_projected_disk_tightly():
    from splatk.backends.planar_cpu import planar_bboxes
    from splatk.backends.planar_torch import splat_homographies

    scene, _ = random_scene(40, seed=9)
    width, height = 400, 320  # no clipping: every disk lies inside the image
    K = torch.tensor([[100.0, 0, width / 2], [0, 100.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    M = splat_homographies(scene["means"], scene["quats"], scene["scales"], scene["viewmat"], K)
    box = planar_bboxes(M, width, height).double()
    assert (box[:, 0] > 0).all() and (box[:, 1] < width).all()  # unclipped
    assert (box[:, 2] > 0).all() and (box[:, 3] < height).all()
    t = torch.linspace(0, 2 * torch.pi, 2000, dtype=torch.float64)
    rim = torch.stack([3 * torch.cos(t), 3 * torch.sin(t), torch.ones_like(t)], 0)  # [3, T]
    p = M @ rim
    xs, ys = p[:, 0] / p[:, 2] - 0.5, p[:, 1] / p[:, 2] - 0.5  # in pixel-index units
    assert ((xs.min(1).values >= box[:, 0] - 1) & (xs.max(1).values <= box[:, 1])).all()
    assert ((ys.min(1).values >= box[:, 2] - 1) & (ys.max(1).values <= box[:, 3])).all()
    # tight: the first and last pixel of each box are within one pixel of the rim
    assert (box[:, 0] - xs.min(1).values <= 1.0 + 1e-6).all() and (xs.max(1).values - (box[:, 1] - 1) <= 1.0 + 1e-6).all()
    assert (box[:, 2] - ys.min(1).values <= 1.0 + 1e-6).all() and (ys.max(1).values - (box[:, 3] - 1) <= 1.0 + 1e-6).all()


def test_native_is_bitwise_reproducible_across_thread_counts():
    """Per-(primitive, tile) gradient slots summed in a fixed order: no atomics, no races."""
    _native_or_skip()
    scene, table = random_scene(60, seed=2, grid=4)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    threads = torch.get_num_threads()
    results = []
    try:
        for t in (1, 2, 3):
            torch.set_num_threads(t)
            results.append(_render(scene, table, "grid", "cpu", torch.float32, bg))
    finally:
        torch.set_num_threads(threads)
    (img0, g0), *rest = results
    for img, g in rest:
        assert torch.equal(img.colors, img0.colors)
        for name in g0:
            assert torch.equal(g[name], g0[name]), name
