"""Which train views draw each primitive of the learned kernel (splatk.train.view_support), and
MCMC's relocation of the primitives one view alone draws (decision 0113)."""
from __future__ import annotations

import math

import pytest
import torch

from splatk import backends
from splatk.train.mcmc import MCMCConfig, MCMCStrategy
from splatk.train.optim import PrimitiveAdam
from splatk.train.view_support import (
    FLOOR,
    effective_peaks,
    one_view_mask,
    one_view_primitives,
)
from tests.scenes import orbit_cameras, random_model


def _model_and_cameras(kernel: str):
    """40 primitives about the origin, five cameras of an orbit of eight (the three facing camera 0
    left out); primitive 0 moved just in front of camera 0, where the others (45 to 90 degrees round
    the orbit, a 25-degree half-field) do not see it."""
    model = random_model(40, seed=3, kernel=kernel)
    orbit = orbit_cameras(8, size=32)
    cams = [orbit[i] for i in (0, 1, 2, 6, 7)]
    centre = cams[0].center
    with torch.no_grad():
        if kernel == "learned":  # latents far from zero, so that the view changes the profiles
            model.prims["z3d"].data[:] = 2.0 * torch.randn(40, model.kernel.latent_dim,
                                                           generator=torch.Generator().manual_seed(0))
        model.prims["means"].data[0] = centre + 0.3 * (-centre / centre.norm())
        model.prims["log_scales"].data[0] = math.log(0.02)
        model.prims["opacity_logits"].data[0] = 3.0
    return model, cams, backends.get("torch")


@torch.no_grad()
def test_effective_peaks_are_opacity_times_the_centre_value_where_a_view_sees_the_primitive():
    model, cams, backend = _model_and_cameras("learned")
    peaks = effective_peaks(model, backend, cams)
    prims = model.prims
    for v, cam in enumerate(cams):
        visible = backend.project(prims["means"], prims["quats"], model.scales, cam.world_to_cam, cam.K,
                                  cam.width, cam.height, support_sigmas=model.kernel.support_sigmas).visible
        assert torch.equal(~peaks[:, v].isnan(), visible)
    seen = peaks[~peaks.isnan()]
    assert seen.numel() > 50 and float(seen.min()) >= 0
    assert float((peaks / model.opacities[:, None]).nan_to_num(0).amax()) <= 1.0
    assert float(seen.std()) > 0.01
    model.prims["opacity_logits"].data[1] += 1.0  # linear in the opacity, each view's d(0) fixed
    raised = effective_peaks(model, backend, cams)
    ratio = (raised[1] / peaks[1])[~peaks[1].isnan()]
    assert ratio.numel() > 1 and torch.allclose(ratio, ratio[:1].expand_as(ratio), rtol=1e-4) and ratio[0] > 1.05


def test_one_view_mask_compares_the_second_peak_with_the_largest():
    nan = float("nan")
    table = torch.tensor([[0.8, 0.1, nan], [0.8, 0.3, 0.2], [0.05, 0.0, nan], [0.5, nan, nan],
                          [nan, nan, nan], [0.1, 0.9, 0.0], [0.0, nan, 0.3]])
    # switched off by the others that see it: yes; drawn alike: no; too faint: no; seen by one
    # view only (a floater of any kernel): no; seen by none: no; the largest anywhere: yes
    assert one_view_mask(table, 0.25, 0.1).tolist() == [True, False, False, False, False, True, True]
    assert not one_view_mask(table[:, :1], 0.25, 0.1).any()  # one camera: nothing to compare


@torch.no_grad()
def test_one_view_primitives_leaves_out_what_one_camera_alone_sees_and_view_independent_kernels():
    model, cams, backend = _model_and_cameras("learned")
    peaks = effective_peaks(model, backend, cams)
    assert int((~peaks[0].isnan()).sum()) == 1 and float(peaks[0].nan_to_num(0).max()) > 0.5  # camera 0 alone
    assert not bool(one_view_primitives(model, backend, cams)[0])
    model, cams, backend = _model_and_cameras("gaussian")
    assert not one_view_primitives(model, backend, cams).any()  # no view dependence: never
    assert not one_view_primitives(model, None, cams).any()  # ... so it draws nothing


def test_one_view_primitives_of_a_learned_model_need_the_ops_that_draw_the_views():
    model, cams, _ = _model_and_cameras("learned")
    with pytest.raises(ValueError, match="backend"):
        one_view_primitives(model, None, cams)


@torch.no_grad()
def test_mcmc_relocates_the_one_view_primitives_and_no_others(monkeypatch):
    """MCMC's dead set takes in what one_view_primitives finds, over the strategy's train views,
    and only with relocate_one_view on."""
    from splatk.train import mcmc

    model, cams, backend = _model_and_cameras("learned")
    found = torch.zeros(model.num_primitives, dtype=torch.bool)
    found[[3, 17]] = True
    asked = []

    def one_view(m, b, views):
        asked.append(len(views))
        return found.clone()

    monkeypatch.setattr(mcmc, "one_view_primitives", one_view)
    for on in (True, False):
        model, cams, backend = _model_and_cameras("learned")
        before = model.prims["means"].detach().clone()
        opt = PrimitiveAdam(model.prims, {**model.learning_rates(), "means": 1e-4})
        config = MCMCConfig(refine_every=1, refine_start=0, relocate_one_view=on, noise_lr=0.0)
        strategy = MCMCStrategy(config, cap_max=40, views=cams, backend=backend)
        strategy.step(1, 0.0, model, opt, means_lr=1e-4, generator=torch.Generator().manual_seed(0))
        moved = (model.prims["means"] != before).any(1)
        assert torch.equal(moved, found if on else torch.zeros_like(found)), on
        assert strategy.last_stats["relocated"] == (2 if on else 0)
    assert asked == [len(cams)]


@torch.no_grad()
def test_one_view_primitives_draws_only_what_can_reach_the_floor_and_finds_the_same():
    """d(0) is at most 1, so primitives under FLOOR's opacity are skipped: the mask must be the one
    the full table gives, over a strongly view-dependent Phi_proj and opacities on both sides."""
    model, cams, backend = _model_and_cameras("learned")
    for weight in model.kernel.proj.parameters():
        weight.mul_(3.0)  # makes d(0) turn with the view: some primitives one view alone draws
    model.prims["opacity_logits"].data[1:] = torch.linspace(-4.0, 3.0, 39)
    full = effective_peaks(model, backend, cams)
    assert torch.equal(effective_peaks(model, backend, cams, torch.tensor([7, 2, 30])).nan_to_num(-1),
                       full[[7, 2, 30]].nan_to_num(-1))
    expected = one_view_mask(full)
    by_ratio_alone = one_view_mask(full, floor=0.0)  # what the opacity cut-off must leave out
    faint = model.opacities < FLOOR
    assert expected.any() and (by_ratio_alone & faint).any()
    assert torch.equal(one_view_primitives(model, backend, cams), expected)
