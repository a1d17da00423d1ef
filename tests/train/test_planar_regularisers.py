"""2DGS's normal consistency and depth distortion for planar primitives, from blended channels:
the moments against brute force, gradcheck, the native backend against the reference, the
trainer paying for them only while they are on, and a short fit that lowers the normal term."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

from splatk import backends
from splatk.backends.planar import PlanarProfile, rasterize_planar
from splatk.backends.planar_torch import planar_visible, ray_splat_uv
from splatk.functional.projection import quats_to_rotmats
from splatk.functional.surfel_depth import inverse_depth_moments, pixel_rays, surfel_geometry_channels
from splatk.models.planar import PlanarModel
from splatk.train.mcmc import MCMCConfig
from splatk.train.planar_regularisers import GeometryTerms, depth_distortion, normal_consistency
from splatk.train.trainer import TrainConfig, Trainer

SURFEL = PlanarProfile("gaussian_surfel")


def _native_or_skip():
    from splatk.backends.cpu_native import available

    if not available():
        pytest.skip("native cpu backend unavailable")


def overlapping_surfels(n: int, width: int, height: int, seed: int = 0, spread: float = 0.6) -> dict:
    """float64 disks in front of an identity camera, large and tilted by up to ~35 degrees from
    facing it, so that several overlap on most pixels."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    f = 3.0 * width
    means = torch.stack([(r(n) - 0.5) * spread, (r(n) - 0.5) * spread, 2.0 + 1.5 * r(n)], 1)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    half = 0.3 * r(n)  # half the turn angle: up to ~34 degrees away from the optical axis
    quats = torch.cat([torch.cos(half)[:, None], torch.sin(half)[:, None] * axis], 1)
    scales = 0.35 + 0.2 * r(n, 2)
    opacities = 0.4 + 0.5 * r(n)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, viewmat=torch.eye(4, dtype=torch.float64),
                K=K)


def render_geometry(s: dict, width: int, height: int, backend: str = "torch"):
    """(geometry [H, W, 12], alphas [H, W, 1]) of the disks in ``s``, one rasteriser call."""
    channels = surfel_geometry_channels(s["means"], s["quats"], s["viewmat"])
    out = rasterize_planar(s["means"], s["quats"], s["scales"], s["opacities"], channels, s["viewmat"], s["K"],
                           width, height, SURFEL, backend=backend)
    return out.colors, out.alphas


def test_moments_equal_the_pairwise_sum_and_the_intersection_depths():
    width, height = 14, 11
    s = overlapping_surfels(5, width, height, seed=3)
    n = s["means"].shape[0]
    # each surfel's blending weight per pixel: composite one-hot colours
    weights = rasterize_planar(s["means"], s["quats"], s["scales"], s["opacities"], torch.eye(n, dtype=torch.float64),
                               s["viewmat"], s["K"], width, height, SURFEL).colors  # [H, W, n]
    # the inverse depth of each (pixel, surfel) pair, from the intersection point itself:
    # (u, v) of 2DGS Eq. 10, then the disk's point p + u s_u t_u + v s_v t_v
    order, M = planar_visible(s["means"], s["quats"], s["scales"], s["viewmat"], s["K"])
    assert order.numel() == n
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                            torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 1, 2).expand(-1, n, 2).reshape(-1, 2)
    uv = ray_splat_uv(M.repeat(height * width, 1, 1), pix).reshape(height, width, n, 2)
    rot = quats_to_rotmats(s["quats"])[order]
    axes = rot[:, :, :2] * s["scales"][order][:, None, :]  # [n, 3, 2]
    points = s["means"][order] + (axes[None, None] @ uv[..., None])[..., 0]  # [H, W, n, 3]
    inv_depth = torch.empty(height, width, n, dtype=torch.float64)
    inv_depth[..., order] = 1.0 / points[..., 2]
    assert (weights > 1e-3).sum(-1).float().mean() > 2.0  # most pixels blend several surfels

    geometry, alphas = render_geometry(s, width, height)
    rays = pixel_rays(s["K"], width, height)
    first, second = inverse_depth_moments(geometry, rays)
    # q . r is each pair's exact inverse depth: every surfel's channels alone
    q = surfel_geometry_channels(s["means"], s["quats"], s["viewmat"])[:, 3:6]
    torch.testing.assert_close(rays @ q.T, inv_depth, rtol=1e-10, atol=0)
    torch.testing.assert_close(first, (weights * inv_depth).sum(-1), rtol=1e-10, atol=1e-13)
    pairwise = 0.5 * (weights[..., :, None] * weights[..., None, :]
                      * (inv_depth[..., :, None] - inv_depth[..., None, :]) ** 2).sum((-1, -2))
    torch.testing.assert_close(alphas[..., 0] * second - first ** 2, pairwise, rtol=1e-8, atol=1e-13)
    assert pairwise.max() > 1e-3  # the surfels' depths differ: the check is not of zeros
    torch.testing.assert_close(depth_distortion(geometry, alphas, rays), pairwise.mean(), rtol=1e-8, atol=0)


def test_normal_consistency_is_zero_on_one_plane_and_not_on_two():
    width, height = 12, 10
    s = overlapping_surfels(2, width, height, seed=0)
    s["means"] = torch.tensor([[0.1, -0.05, 2.0], [0.0, 0.1, 1.8]], dtype=torch.float64)
    s["scales"] = torch.tensor([[0.6, 0.6], [0.6, 0.6]], dtype=torch.float64)
    s["opacities"] = torch.tensor([0.9, 0.5], dtype=torch.float64)
    s["quats"] = torch.tensor([[math.cos(0.2), math.sin(0.2), 0, 0], [math.cos(0.2), 0, -math.sin(0.2), 0]],
                              dtype=torch.float64)  # turned 0.4 rad about x, and about y
    rays = pixel_rays(s["K"], width, height)
    one = {k: (v[:1] if k in ("means", "quats", "scales", "opacities") else v) for k, v in s.items()}
    geometry, alphas = render_geometry(one, width, height)
    assert alphas.min() > 0.02  # the plane covers every pixel (above COVERAGE_MIN)
    alone = float(normal_consistency(geometry, alphas, rays))
    crossing = float(normal_consistency(*render_geometry(s, width, height), rays))
    assert abs(alone) < 1e-10  # a tilted plane's depth map has the plane's normal everywhere
    assert crossing > 1e-2, crossing


def _term_of_params(term, width, height, base, backend="torch"):
    def f(means, quats, scales, opacities):
        s = dict(base, means=means, quats=quats, scales=scales, opacities=opacities)
        geometry, alphas = render_geometry(s, width, height, backend)
        return term(geometry, alphas, pixel_rays(s["K"], width, height))
    return f


@pytest.mark.parametrize("term", [normal_consistency, depth_distortion], ids=["normal", "distortion"])
def test_gradcheck_float64_torch_backend(term):
    width, height = 7, 6
    s = overlapping_surfels(3, width, height, seed=1, spread=0.2)
    inputs = tuple(s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities"))
    f = _term_of_params(term, width, height, s)
    geometry, alphas = render_geometry(s, width, height)
    assert alphas.min() > 0.05  # every pixel well above COVERAGE_MIN: the normal term keeps its pixels
    assert float(f(*inputs).detach()) > 1e-6
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("term", [normal_consistency, depth_distortion], ids=["normal", "distortion"])
def test_cpu_backend_terms_match_the_torch_reference(term):
    _native_or_skip()
    width, height = 30, 24
    s = overlapping_surfels(12, width, height, seed=2, spread=1.5)
    results = {}
    for backend in ("torch", "cpu"):
        inputs = tuple(s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities"))
        value = _term_of_params(term, width, height, s, backend)(*inputs)
        value.backward()
        results[backend] = (value.detach(), [x.grad for x in inputs])
    ref, nat = results["torch"], results["cpu"]
    assert float(ref[0]) > 1e-6
    torch.testing.assert_close(nat[0], ref[0], rtol=1e-9, atol=1e-12)
    for g_nat, g_ref in zip(nat[1], ref[1]):
        assert g_ref.abs().max() > 0
        torch.testing.assert_close(g_nat, g_ref, rtol=1e-8, atol=1e-10)


def test_geometry_channels_leave_the_image_unchanged():
    scene = synthetic_scene(num_views=4, size=16)
    torch.manual_seed(0)
    model = PlanarModel.from_points(scene.points, scene.point_colors, color_options={"sh_degree": 1})
    bg = torch.tensor(scene.background)
    with torch.no_grad():
        plain = model.render(scene.train[0], bg, backend=backends.get("torch"))
        geo = model.render(scene.train[0], bg, backend=backends.get("torch"), geometry=True)
    assert plain.geometry is None and geo.geometry.shape == (16, 16, 12)
    torch.testing.assert_close(geo.image, plain.image, rtol=0, atol=1e-6)
    torch.testing.assert_close(geo.alpha, plain.alpha, rtol=0, atol=0)
    # the blended normals are unit normals weighted by blending weights summing to alpha
    assert bool((geo.geometry[..., :3].norm(dim=-1) <= geo.alpha[..., 0] + 1e-5).all())


def test_geometry_terms_are_on_after_their_start_with_a_weight():
    terms = GeometryTerms(normal_weight=0.05, normal_from=10, distortion_weight=0.0, distortion_from=0)
    assert not terms.wanted(10) and terms.wanted(11)
    assert terms.normal_on(11) and not terms.distortion_on(11)
    assert not GeometryTerms(0.0, 0, 0.0, 0).wanted(100)


def _fit(scene, normal_weight: float, iters: int, calls: list | None = None):
    torch.manual_seed(0)
    model = PlanarModel.from_points(scene.points, scene.point_colors, color="sh", color_options={"sh_degree": 1})
    if calls is not None:
        render = model.render

        def recording_render(*args, **kwargs):
            calls.append(kwargs.get("geometry", False))
            return render(*args, **kwargs)
        model.render = recording_render
    cfg = TrainConfig(iters=iters, budget=120, backend="auto", normal_weight=normal_weight, normal_from=iters // 3,
                      mcmc=MCMCConfig(refine_start=50, refine_every=25))
    tr = Trainer(scene, model, cfg)
    logged = []
    tr.run(on_step=logged.append)
    return tr, logged


def _mean_normal_loss(model, cams, background) -> float:
    values = []
    with torch.no_grad():
        for cam in cams:
            out = model.render(cam, background, backend=backends.get("auto"), geometry=True)
            values.append(float(normal_consistency(out.geometry, out.alpha, pixel_rays(cam.K, cam.width, cam.height))))
    return sum(values) / len(values)


def _mean_psnr(model, cams, background) -> float:
    values = []
    with torch.no_grad():
        for cam in cams:
            img = model.render(cam, background, backend=backends.get("auto")).image.clamp(0, 1)
            values.append(float(-10 * torch.log10(((img - cam.image_float()) ** 2).mean())))
    return sum(values) / len(values)


def test_a_short_fit_with_the_normal_term_lowers_it_and_still_fits():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = synthetic_scene(num_views=8, size=24)
        iters = 240
        calls: list = []
        on, logged = _fit(scene, 0.2, iters, calls)
        off, _ = _fit(scene, 0.0, iters)
    finally:
        torch.set_num_threads(threads)
    bg = torch.tensor(scene.background)
    # the channels are rendered only once the term is on (iterations after normal_from = 80)
    assert calls == [False] * 80 + [True] * (iters - 80)
    assert logged[79].normal_loss is None and logged[80].normal_loss is not None
    assert logged[-1].distortion_loss is None
    loss_on, loss_off = _mean_normal_loss(on.model, scene.train, bg), _mean_normal_loss(off.model, scene.train, bg)
    assert loss_on < 0.7 * loss_off, (loss_on, loss_off)
    psnr_on, psnr_off = _mean_psnr(on.model, scene.test, bg), _mean_psnr(off.model, scene.test, bg)
    assert psnr_on > 20.0 and psnr_on > psnr_off - 1.0, (psnr_on, psnr_off)


def test_a_term_switching_on_is_no_divergence():
    """A heavy normal term lifts the loss many times over at its start; the guard judges the
    loss without the geometry terms, so that step is no rollback."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = synthetic_scene(num_views=8, size=24)
        tr, logged = _fit(scene, 1.0, 150)
    finally:
        torch.set_num_threads(threads)
    assert logged[50].normal_loss is not None
    jump = logged[50].loss / logged[49].loss
    assert jump > 2.0, jump  # judged with the term, the guard rolled this run back four times
    assert not tr.events, tr.events
