"""Primitives close to a train camera for their size (splatk.train.near_cameras), and MCMC's
relocation of them."""
from __future__ import annotations

import math

import torch

from splatk.functional.projection import covariances_3d
from splatk.train.mcmc import MCMCConfig, MCMCStrategy
from splatk.train.near_cameras import CLOSE_SUPPORTS, close_to_cameras
from splatk.train.optim import PrimitiveAdam
from tests.scenes import orbit_cameras, random_model


def _place(model, index: int, centre: torch.Tensor, scale: float) -> None:
    with torch.no_grad():
        model.prims["means"].data[index] = centre
        model.prims["log_scales"].data[index] = math.log(scale)


def _in_front_of(cam, distance: float) -> torch.Tensor:
    """The point ``distance`` along camera ``cam``'s optical axis."""
    axis = cam.world_to_cam[2, :3]  # the camera's z axis in world coordinates
    return cam.center + distance * axis


@torch.no_grad()
def test_close_is_depth_under_three_support_radii_whatever_the_kernel_support():
    cams = orbit_cameras(6, size=32)
    for kernel, support in (("gaussian", 3.0), ("learned", 1.0)):
        model = random_model(20, seed=1, kernel=kernel)
        assert model.kernel.support_sigmas == support
        # 0.3 in front of camera 0: close when 3 x support x scale > 0.3
        _place(model, 0, _in_front_of(cams[0], 0.3), 0.3 / (CLOSE_SUPPORTS * support) * 1.2)
        _place(model, 1, _in_front_of(cams[0], 0.3), 0.3 / (CLOSE_SUPPORTS * support) * 0.8)
        _place(model, 2, cams[0].center - 0.3 * cams[0].world_to_cam[2, :3], 0.2)  # behind it
        mask = close_to_cameras(model, cams)
        assert mask[0] and not mask[1] and not mask[2], kernel


@torch.no_grad()
def test_a_primitive_that_holds_a_camera_never_counts():
    cams = orbit_cameras(6, size=32)
    model = random_model(20, seed=1, kernel="learned")
    _place(model, 0, _in_front_of(cams[0], 0.3), 0.2)  # close to camera 0, camera outside it
    assert close_to_cameras(model, cams)[0]
    _place(model, 0, _in_front_of(cams[0], 0.3), 0.31)  # camera 0 inside its 1-sigma support
    assert not close_to_cameras(model, cams)[0]
    _place(model, 0, _in_front_of(cams[0], 0.3), 0.29)  # just outside again
    assert close_to_cameras(model, cams)[0]


@torch.no_grad()
def test_close_to_cameras_matches_the_definition_written_out():
    """Against depth and the covariance's inverse, one primitive and camera at a time, over a
    model scaled so that some primitives are close, some hold a camera and most neither."""
    cams = orbit_cameras(5, size=32, radius=2.0)
    for kernel in ("gaussian", "learned"):
        model = random_model(200, seed=4, kernel=kernel)
        with torch.no_grad():
            model.prims["means"].data *= 3.0
            model.prims["log_scales"].data += torch.linspace(-1.0, 2.5, 200)[:, None]
        support = model.kernel.support_sigmas
        cov = covariances_3d(model.prims["quats"], model.scales).double()
        radius = support * model.scales.max(1).values
        expected = []
        for i in range(model.num_primitives):
            close = holds = False
            for cam in cams:
                depth = float(cam.world_to_cam[2, :3] @ model.prims["means"][i] + cam.world_to_cam[2, 3])
                close |= 0 < depth < CLOSE_SUPPORTS * float(radius[i])
                d = (cam.center - model.prims["means"][i]).double()
                holds |= float(d @ torch.linalg.solve(cov[i], d)) <= support * support
            expected.append(close and not holds)
        expected = torch.tensor(expected)
        assert 5 < int(expected.sum()) < 195, kernel
        assert torch.equal(close_to_cameras(model, cams), expected), kernel


@torch.no_grad()
def test_mcmc_relocates_the_primitives_close_to_a_train_camera_only_when_asked():
    cams = orbit_cameras(6, size=32)
    for on in (True, False):
        model = random_model(40, seed=3, kernel="gaussian")
        _place(model, 5, _in_front_of(cams[2], 0.2), 0.05)
        found = close_to_cameras(model, cams)
        assert found[5] and int(found.sum()) < 10
        before = model.prims["means"].detach().clone()
        opt = PrimitiveAdam(model.prims, {**model.learning_rates(), "means": 1e-4})
        config = MCMCConfig(refine_every=1, refine_start=0, relocate_near_cameras=on, noise_lr=0.0)
        strategy = MCMCStrategy(config, cap_max=40, views=cams, backend=None)
        strategy.step(1, 0.0, model, opt, means_lr=1e-4, generator=torch.Generator().manual_seed(0))
        moved = (model.prims["means"] != before).any(1)
        assert torch.equal(moved, found if on else torch.zeros_like(found)), on
        assert not close_to_cameras(model, cams)[5] or not on
