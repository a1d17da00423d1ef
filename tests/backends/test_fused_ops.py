"""The fused native ops of the cpu backend (SSIM, EWA projection, SH colour) against their torch
references: values and gradients to float tolerance, and float64 gradcheck of the hand-written
backward passes."""
import math

import pytest
import torch

from splatk import backends
from splatk.backends import cpu_native
from splatk.functional.projection import project_ellipsoids, quats_to_rotmats
from splatk.functional.sh import eval_sh
from splatk.metrics.ssim import ssim

pytestmark = pytest.mark.skipif(not cpu_native.available(), reason="native extension unavailable")

from splatk.backends.fused_cpu import eval_sh_fused, project_ellipsoids_fused, ssim_mean_fused  # noqa: E402

TOL = {torch.float64: 1e-10, torch.float32: 2e-5}


def _camera(dtype, th=0.3):
    vm = torch.eye(4, dtype=dtype)
    vm[:3, :3] = torch.tensor([[math.cos(th), 0, math.sin(th)], [0, 1, 0],
                               [-math.sin(th), 0, math.cos(th)]], dtype=dtype)
    vm[:3, 3] = torch.tensor([0.1, -0.2, 0.5], dtype=dtype)
    K = torch.tensor([[300, 0, 160], [0, 310, 120], [0, 0, 1.0]], dtype=dtype)
    return vm, K


def _ellipsoids(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    # centres spread so that some are behind the camera, off-screen, or clamped by the
    # Jacobian's frustum guard; scales from sub-pixel to large
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 3 + torch.tensor([0, 0, 4.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.4 + 0.005
    return [t.requires_grad_() for t in (means, quats, scales)]


def _rel(a, b):
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(37, 53), (11, 11), (64, 16)])
def test_ssim_matches_reference(dtype, size):
    g = torch.Generator().manual_seed(1)
    x = torch.rand(*size, 3, generator=g, dtype=dtype).requires_grad_()
    y = (x.detach() + 0.1 * torch.randn(*size, 3, generator=g, dtype=dtype)).clamp(0, 1)
    fused = ssim_mean_fused(x, y)
    ref = ssim(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None]).mean()
    assert abs(float(fused.detach() - ref.detach())) < TOL[dtype]
    (g_fused,) = torch.autograd.grad(fused, x)
    (g_ref,) = torch.autograd.grad(ref, x)
    assert _rel(g_fused, g_ref) < 10 * TOL[dtype]


def test_ssim_gradcheck():
    x = torch.rand(9, 13, 3, dtype=torch.float64, requires_grad=True)
    y = torch.rand(9, 13, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: ssim_mean_fused(a, y, window_size=5), (x,))


def _reach(means, quats, scales, vm, support):
    """The support's reach along the view axis: support x the camera-space sigma in depth."""
    M = (vm[:3, :3] @ quats_to_rotmats(quats.detach())) * scales.detach()[:, None, :]
    return support * (M[:, 2] ** 2).sum(-1).sqrt()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("support", [3.0, 1.0])
def test_projection_matches_reference(dtype, support):
    means, quats, scales = _ellipsoids(2000, dtype)
    with torch.no_grad():  # a hundred large primitives just in front of the camera
        means[:100, 2] = means[:100, 2].abs() * 0.05 - 0.25
        means[:100, :2] *= 0.1
        scales[:100] += 0.3
    vm, K = _camera(dtype)
    ref = project_ellipsoids(means, quats, scales, vm, K, 320, 240, support_sigmas=support)
    m2, co, dp, vis, mc, rc = project_ellipsoids_fused(means, quats, scales, vm, K, 320, 240,
                                                       support_sigmas=support, want_view=True)
    assert torch.equal(vis, ref.visible)
    assert 100 < int(vis.sum()) < 2000  # the scene exercises both branches
    # ... and primitives whose support reaches across the camera plane, where the first-order
    # projection is furthest from its expansion point (kangaroo's veils, decisions 0110-0120)
    crossing = _reach(means, quats, scales, vm, support) > dp.detach().clamp_min(0.01)
    assert 20 < int((crossing & vis).sum()) < int(vis.sum())
    v = vis
    outs = (m2, co, dp, mc, rc)
    refs = (ref.means2d, ref.conics, ref.depths, ref.means_cam, ref.rotmats_cam)
    for a, b in zip(outs, refs):
        assert _rel(a[v], b[v]) < TOL[dtype]
    g = torch.Generator().manual_seed(2)
    w = [torch.randn(t.shape, generator=g, dtype=dtype) * v.view(-1, *[1] * (t.dim() - 1))
         for t in outs]

    def loss(a, b, c, d, e):  # conics are ~1e-3: scale them up so their gradients count
        return ((a * w[0]).sum() + 1e3 * (b * w[1]).sum() + (c * w[2]).sum() + (d * w[3]).sum()
                + (e * w[4]).sum())

    g_fused = torch.autograd.grad(loss(*outs), (means, quats, scales))
    g_ref = torch.autograd.grad(loss(*refs), (means, quats, scales))
    for a, b in zip(g_fused, g_ref):
        assert _rel(a, b) < 20 * TOL[dtype]


def test_projection_gradcheck_where_the_support_reaches_the_camera():
    """The hand-written backward for primitives whose support reaches across the camera plane,
    where the Jacobian's 1/z and x/z^2 terms are largest."""
    means, quats, scales = _ellipsoids(6, torch.float64, seed=3)
    with torch.no_grad():
        means[:, 2] = means[:, 2].abs() * 0.05 + 0.2  # in front, nearer than the support reaches
        means[:, :2] *= 0.03
        scales.mul_(2.0).add_(0.3)
    vm, K = torch.eye(4, dtype=torch.float64), _camera(torch.float64)[1]
    assert bool((_reach(means, quats, scales, vm, 3.0) > means[:, 2].detach() * 1.2).all())

    def f(m, q, s):
        a, b, c, _, d, e = project_ellipsoids_fused(m, q, s, vm, K, 320, 240, want_view=True)
        return a, 1e3 * b, c, d, e

    assert torch.autograd.gradcheck(f, (means, quats, scales))


def test_projection_gradcheck():
    means, quats, scales = _ellipsoids(6, torch.float64, seed=3)
    with torch.no_grad():
        means[:, 2] = means[:, 2].abs() + 2  # all in front, so every output is smooth
        means[:, :2] *= 0.3
    vm, K = _camera(torch.float64)

    def f(m, q, s):
        a, b, c, _, d, e = project_ellipsoids_fused(m, q, s, vm, K, 320, 240, want_view=True)
        return a, 1e3 * b, c, d, e

    assert torch.autograd.gradcheck(f, (means, quats, scales))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_reference(dtype, degree):
    g = torch.Generator().manual_seed(degree)
    n = 300
    sh0 = torch.randn(n, 1, 3, generator=g, dtype=dtype).requires_grad_()
    rest = (0.3 * torch.randn(n, 15, 3, generator=g, dtype=dtype)).requires_grad_()
    dirs = torch.randn(n, 3, generator=g, dtype=dtype).requires_grad_()
    ref = eval_sh(torch.cat([sh0, rest], 1), dirs, degree)
    fused = eval_sh_fused(sh0, rest, dirs, degree)
    assert _rel(fused, ref) < TOL[dtype]
    assert bool((ref == 0).any())  # some colours clamp at zero: the mask is exercised
    w = torch.randn(n, 3, generator=g, dtype=dtype)
    kw = dict(allow_unused=True, materialize_grads=True)
    g_ref = torch.autograd.grad((ref * w).sum(), (sh0, rest, dirs), **kw)
    g_fused = torch.autograd.grad((fused * w).sum(), (sh0, rest, dirs), **kw)
    for a, b in zip(g_fused, g_ref):
        assert float((a - b).abs().max()) < 10 * TOL[dtype] * max(1.0, float(b.abs().max()))


def test_sh_gradcheck():
    g = torch.Generator().manual_seed(5)
    sh0 = torch.randn(5, 1, 3, generator=g, dtype=torch.float64).requires_grad_()
    rest = torch.randn(5, 15, 3, generator=g, dtype=torch.float64).requires_grad_()
    dirs = torch.randn(5, 3, generator=g, dtype=torch.float64).requires_grad_()
    with torch.no_grad():
        sh0 += 3.0  # away from the clamp at zero, where the function has a kink
    assert torch.autograd.gradcheck(lambda a, b, c: eval_sh_fused(a, b, c, 3), (sh0, rest, dirs))


@pytest.mark.parametrize("kernel", ["gaussian", "learned"])
def test_cpu_render_matches_torch_render(kernel):
    """A whole render through the fused path equals the pure-torch path, image and gradients
    (the learned kernel also takes camera-space centres and rotations from the projection)."""
    from splatk.models.volumetric import SplatModel
    from tests.scenes import synthetic_scene

    scene = synthetic_scene(num_views=2)
    torch.manual_seed(0)
    m = SplatModel.from_points(scene.points, scene.point_colors, kernel=kernel,
                               color_options={"sh_degree": 3})
    with torch.no_grad():  # anisotropic, rotated, view-dependent: every gradient is non-trivial
        m.prims["sh_rest"].normal_(0, 0.1)
        m.prims["log_scales"].add_(torch.randn_like(m.prims["log_scales"]) * 0.5)
        m.prims["quats"].normal_()
        if "z3d" in m.prims:
            m.prims["z3d"].normal_(0, 0.5)
    cam = scene.train[0]
    bg = torch.tensor(scene.background)
    grads = []
    images = []
    for backend in ("cpu", "torch"):
        m.zero_grad()
        out = m.render(cam, bg, sh_degree=3, backend=backends.get(backend))
        (out.image * torch.linspace(0, 1, out.image.numel()).view_as(out.image)).sum().backward()
        images.append(out.image.detach())
        grads.append({k: p.grad.clone() for k, p in m.prims.items()})
    assert _rel(images[0], images[1]) < 1e-5
    for k in grads[0]:
        assert _rel(grads[0][k], grads[1][k]) < 1e-3, k
    with torch.no_grad():  # eval renders (the learned kernel's native encode / decode)
        if kernel == "learned":  # Phi_proj in bf16 where the CPU has it: native vs autocast rounding
            a, b = (m.render(cam, bg, sh_degree=3, backend=backends.get(be)).image for be in ("cpu", "torch"))
            assert _rel(a, b) < 1e-3
            m.kernel.proj_precision = "fp32"
        a, b = (m.render(cam, bg, sh_degree=3, backend=backends.get(be)).image for be in ("cpu", "torch"))
    assert _rel(a, b) < 1e-5


@pytest.mark.parametrize("inputs", ["z,mu,s,R", "mu,s", "z", "R,z"])
def test_learned_encode_and_decode_match_torch(inputs):
    """Renders without gradients take Phi_proj's inputs and Phi_dec's samples from native
    passes; they equal the torch ops (kernels/learned.py) to float tolerance."""
    from splatk.kernels import ViewContext, make_kernel

    g = torch.Generator().manual_seed(1)
    m = 300
    mu = torch.randn(m, 3, generator=g) * 2 + torch.tensor([0, 0, 5.0])
    mu[0] = 0.0  # rho clamped at 1e-12
    view = ViewContext(mu, torch.rand(m, 3, generator=g) * 0.3 + 1e-4,
                       torch.linalg.qr(torch.randn(m, 3, 3, generator=g))[0])
    for k in (2, 4, 8):
        kern = make_kernel("learned", k=k, proj_inputs=inputs, weights="none", proj_precision="fp32")
        z = torch.randn(m, 5, generator=g) if "z" in inputs else None
        with torch.no_grad():
            x_ref = kern.encode(z, view)
            fused = ViewContext(view.means_cam, view.scales, view.rotmats_cam, backends.get("cpu"))
            x = kern.encode(z, fused)
            assert x.shape == x_ref.shape and _rel(x, x_ref) < 1e-6
            z2d = kern.project(z, view)
            d_ref = kern.samples(z2d)  # Phi_dec at the k radii, the edge bounded
            d = kern.profile({"z3d": z} if z is not None else {}, fused).params
            assert d.shape == (m, k) and (d - d_ref).abs().max() < 1e-6


def test_learned_fused_ops_refuse_gradients():
    from splatk.backends.fused_cpu import learned_encode_fused

    mu = torch.rand(4, 3, requires_grad=True)
    with pytest.raises(RuntimeError, match="no backward"):
        learned_encode_fused(None, mu, torch.rand(4, 3), torch.rand(4, 3, 3), True, True, True, 2.5, 5.0, 2.5)


@pytest.mark.parametrize("inputs,arch", [("z,mu,s,R", {}), ("mu,s", {}), ("R,z", {}),
                                         ("z,mu,s,R", {"proj_width": 40, "latent2d_dim": 3})])
def test_learned_bf16_profile_matches_autocast(inputs, arch):
    """The native bf16 Phi_proj (one pass: encode, Phi_proj, Phi_dec) computes what torch's CPU
    autocast computes: same profile up to bf16 rounding, and exactly as far from fp32 on average
    (a wrong weight layout or activation would be off by orders of magnitude more)."""
    from splatk.backends.fused_cpu import bf16_mlp_available
    from splatk.kernels import ViewContext, make_kernel

    if not bf16_mlp_available():
        pytest.skip("native build without AVX-512 BF16")
    g = torch.Generator().manual_seed(2)
    m = 300  # not a multiple of the 16-row blocks
    mu = torch.randn(m, 3, generator=g) * 2 + torch.tensor([0, 0, 5.0])
    view = ViewContext(mu, torch.rand(m, 3, generator=g) * 0.3 + 1e-4,
                       torch.linalg.qr(torch.randn(m, 3, 3, generator=g))[0])
    fused = ViewContext(view.means_cam, view.scales, view.rotmats_cam, backends.get("cpu"))
    for k in (2, 8):
        kern = make_kernel("learned", k=k, proj_inputs=inputs, weights="none", proj_precision="bf16", **arch)
        prims = {"z3d": torch.randn(m, kern.latent_dim, generator=g)} if "z" in inputs else {}
        with torch.no_grad():
            native = kern.profile(prims, fused).params
            autocast = kern.profile(prims, view).params
            kern.proj_precision = "fp32"
            exact = kern.profile(prims, view).params
        assert native.shape == (m, k)
        assert (native - autocast).abs().max() < 1e-2
        err_native, err_autocast = (native - exact).abs().mean(), (autocast - exact).abs().mean()
        assert err_native <= 1.2 * err_autocast + 1e-5, (err_native, err_autocast)


def test_learned_bf16_profile_handles_empty_and_single_rows():
    from splatk.backends.fused_cpu import bf16_mlp_available
    from splatk.kernels import ViewContext, make_kernel

    if not bf16_mlp_available():
        pytest.skip("native build without AVX-512 BF16")
    kern = make_kernel("learned", k=4, proj_precision="bf16")
    for m in (0, 1, 17):
        cam = (torch.rand(m, 3) + torch.tensor([0, 0, 3.0]), torch.rand(m, 3) * 0.1 + 0.01,
               torch.eye(3).expand(m, 3, 3).contiguous())
        with torch.no_grad():
            d = kern.profile({"z3d": torch.zeros(m, kern.latent_dim)}, ViewContext(*cam, backends.get("cpu"))).params
            ref = kern.profile({"z3d": torch.zeros(m, kern.latent_dim)}, ViewContext(*cam)).params
        assert d.shape == (m, 4) and (m == 0 or (d - ref).abs().max() < 1e-2)


def test_learned_profile_wider_than_native_buffers_falls_back_to_torch():
    from splatk.kernels import ViewContext, make_kernel

    kern = make_kernel("learned", k=2, proj_width=300, weights="none", proj_precision="bf16")
    assert not kern._fits_native_profile()
    m = 20
    cam = (torch.rand(m, 3) + torch.tensor([0, 0, 3.0]), torch.rand(m, 3) * 0.1 + 0.01,
           torch.eye(3).expand(m, 3, 3).contiguous())
    with torch.no_grad():
        a = kern.profile({"z3d": torch.zeros(m, kern.latent_dim)}, ViewContext(*cam, backends.get("cpu"))).params
        b = kern.profile({"z3d": torch.zeros(m, kern.latent_dim)}, ViewContext(*cam)).params
    assert (a - b).abs().max() < 1e-6  # torch Phi_proj either way (the decode may be native)
