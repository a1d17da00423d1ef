"""The learned kernel's k profile samples, interpolated by the rasteriser's table path, against
Phi_dec evaluated directly at each pixel's r (paper Eqs. 6-8), on a rendered single primitive."""
import math

import pytest
import torch

from splatk import backends
from splatk.data.types import Camera
from splatk.functional.projection import project_ellipsoids
from splatk.kernels import ViewContext
from splatk.models.volumetric import SplatModel


# float32 render of one splat: alpha = o * lerp(table, r); the composited alpha 1 - exp(log1p(-a))
# goes through float64 and back, so a few ulps of 1.0 (~1e-7); 1e-5 leaves room for r2's rounding.
TOL = {torch.float32: 1e-5}


def single_primitive_scene(k: int, seed: int = 0):
    """One learned-kernel primitive, perturbed z3d, seen head-on by a 40x40 camera."""
    g = torch.Generator().manual_seed(seed)
    model = SplatModel.from_points(torch.zeros(1, 3), torch.rand(1, 3, generator=g), kernel="learned",
                                   kernel_options={"k": k}, color="sh", color_options={"sh_degree": 1})
    with torch.no_grad():
        model.prims["means"].data[:] = torch.tensor([[0.1, -0.05, 3.0]])
        model.prims["log_scales"].data[:] = torch.log(torch.tensor([[0.9, 0.6, 0.7]]))
        model.prims["quats"].data[:] = torch.randn(1, 4, generator=g)
        model.prims["opacity_logits"].data[:] = 2.0
        model.prims["z3d"].data[:] = 1.5 * torch.randn(1, 5, generator=g)
    cam = Camera("c", 40, 40, 30.0, 30.0, 20.0, 20.0, torch.eye(4))
    return model, cam


def pixel_r(model, cam):
    """r of every pixel centre w.r.t. the primitive's normalised conic, [H, W]."""
    proj = project_ellipsoids(model.prims["means"], model.prims["quats"], model.scales,
                              cam.world_to_cam, cam.K, cam.width, cam.height,
                              support_sigmas=model.kernel.support_sigmas)
    ys, xs = torch.meshgrid(torch.arange(cam.height) + 0.5, torch.arange(cam.width) + 0.5, indexing="ij")
    dx, dy = xs - proj.means2d[0, 0], ys - proj.means2d[0, 1]
    a, b, c = proj.conics[0]
    r2 = a * dx * dx + 2 * b * dx * dy + c * dy * dy
    return r2, proj


@pytest.mark.parametrize("k", [2, 4, 8])
def test_rendered_alpha_is_interpolated_phi_dec(k):
    model, cam = single_primitive_scene(k)
    with torch.no_grad():
        out = model.render(cam, torch.zeros(3), sh_degree=1, backend=backends.get("torch"))
        r2, proj = pixel_r(model, cam)
        view = ViewContext(proj.means_cam, model.scales, proj.rotmats_cam)
        z2d = model.kernel.project(model.prims["z3d"], view)
        table = model.kernel.samples(z2d)[0]  # [k], paper Eq. 7, the edge sample bounded
        profile = model.kernel.profile(dict(model.prims), view)
        assert torch.equal(profile.params[0], table)
        r = r2.clamp_min(0).sqrt()
        t = r * (k - 1)
        i = t.floor().long().clamp(0, k - 2)
        lam = t - i
        interp = (1 - lam) * table[i] + lam * table[i + 1]  # paper Eq. 8
        direct = model.kernel.decode(z2d, r2.clamp(0, 1).flatten())[0].view_as(r2)  # Phi_dec(r^2)
    o = float(model.opacities[0].detach())
    alpha = out.alpha[..., 0]
    expected = (o * interp).clamp(max=0.999)
    # pixels clearly inside the support and above the 1/255 cut (no threshold ambiguity)
    inside = (r2 < 1 - 1e-4) & (expected > 1 / 255 + 1e-4)
    assert int(inside.sum()) > 100
    assert (alpha[r2 >= 1 + 1e-4] == 0).all()
    # the interpolant: exact up to float rounding
    assert (alpha[inside] - expected[inside]).abs().max() <= TOL[torch.float32]
    # Phi_dec at the pixel's r: within the interpolation error of the table
    with torch.no_grad():
        fine = torch.linspace(0, 1, 2001)
        tf = fine * (k - 1)
        fi = tf.floor().long().clamp(0, k - 2)
        lf = tf - fi
        lerp = (1 - lf) * table[fi] + lf * table[fi + 1]
        bound = (lerp - model.kernel.decode(z2d, fine * fine)[0]).abs().max()
    err = (alpha[inside] - o * direct[inside]).abs().max()
    assert err <= o * bound + TOL[torch.float32]


def test_interpolation_error_shrinks_with_k():
    bounds = []
    for k in (2, 4, 8):
        model, cam = single_primitive_scene(k)
        with torch.no_grad():
            r2, proj = pixel_r(model, cam)
            view = ViewContext(proj.means_cam, model.scales, proj.rotmats_cam)
            z2d = model.kernel.project(model.prims["z3d"], view)
            fine = torch.linspace(0, 1, 1001)
            table = model.kernel.decode(z2d, model.kernel.radii2)[0]
            tf = fine * (k - 1)
            fi = tf.floor().long().clamp(0, k - 2)
            lerp = (1 - (tf - fi)) * table[fi] + (tf - fi) * table[fi + 1]
            bounds.append(float((lerp - model.kernel.decode(z2d, fine * fine)[0]).abs().max()))
    assert bounds[0] > bounds[1] > bounds[2]
    assert math.isfinite(bounds[0])
