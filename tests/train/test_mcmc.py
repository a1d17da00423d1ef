"""MCMC density control: the split rule of relocated / added copies."""
from __future__ import annotations

import math

import pytest
import torch

from splatk import backends
from splatk.train.mcmc import MCMCConfig, MCMCStrategy, split_scale_factor
from splatk.train.optim import PrimitiveAdam

from tests.scenes import orbit_cameras, random_model


def eq9_factor(o: float, n: int) -> float:
    """3DGS-MCMC Eq. 9 as printed (double sum over i, k), for one source split into n copies."""
    o_new = 1.0 - (1.0 - o) ** (1.0 / n)
    denom = sum(math.comb(i - 1, k) * (-1) ** k * o_new ** (k + 1) / math.sqrt(k + 1)
                for i in range(1, n + 1) for k in range(i))
    return o / denom


@pytest.mark.parametrize("o", [0.02, 0.3, 0.7, 0.95, 0.995])
def test_split_scale_factor_matches_eq9(o):
    n = torch.arange(1, 52)
    o_t = torch.full((51,), o, dtype=torch.float64)
    o_new = 1.0 - (1.0 - o_t) ** (1.0 / n.double())
    got = split_scale_factor(o_t, o_new, n)
    want = torch.tensor([eq9_factor(o, int(k)) for k in n], dtype=torch.float64)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    assert got[0] == pytest.approx(1.0, abs=1e-12)  # one copy is the source itself
    assert bool((got[1:] < 1.0).all())  # stacked copies must shrink


def _split_into(copies: int, rule: str, kernel: str = "gaussian"):
    """A one-primitive model grown by MCMC's add step into ``copies`` stacked copies."""
    model = random_model(1, seed=3, kernel=kernel)
    with torch.no_grad():
        model.prims["means"].zero_()
        model.prims["log_scales"].fill_(math.log(0.4))
        model.prims["opacity_logits"].fill_(math.log(0.9 / 0.1))
    before = {k: v.detach().clone() for k, v in model.prims.items()}
    lrs = {**model.learning_rates(), "means": 1e-4}  # the trainer adds the means (scene extent)
    opt = PrimitiveAdam(model.prims, lrs)
    strategy = MCMCStrategy(MCMCConfig(growth=float(copies), split_scales=rule), cap_max=copies)
    assert strategy.add(model, opt) == copies - 1
    return model, before


@torch.no_grad()
def test_shrunk_split_draws_what_the_source_drew():
    """Kept scales make stacked copies draw a fatter blob; Eq. 9's shrink stays much closer."""
    cam = orbit_cameras(1, size=48)[0]
    bg = torch.zeros(3)
    errors = {}
    for rule in ("keep", "shrink"):
        model, before = _split_into(4, rule)
        one = random_model(1, seed=3)
        for k, v in before.items():
            one.prims[k].data.copy_(v)
        ref = one.render(cam, bg, sh_degree=1, backend=backends.get("torch")).image
        img = model.render(cam, bg, sh_degree=1, backend=backends.get("torch")).image
        errors[rule] = float((img - ref).abs().mean())
    assert errors["shrink"] < 0.5 * errors["keep"], errors


def test_keep_is_the_default_and_shrink_works_for_any_kernel():
    assert MCMCConfig().split_scales == "keep"
    kept, before = _split_into(3, "keep", "gaussian")  # DBS's rule: only the opacity splits
    torch.testing.assert_close(kept.prims["log_scales"], before["log_scales"].expand_as(kept.prims["log_scales"]))
    assert bool((kept.prims["opacity_logits"] < before["opacity_logits"]).all())
    for kernel in ("gaussian", "beta"):
        model, before = _split_into(3, "shrink", kernel)
        assert bool((model.prims["log_scales"] < before["log_scales"]).all()), kernel
    with pytest.raises(ValueError, match="split_scales"):
        _split_into(2, "sometimes")


@pytest.mark.parametrize("hold", [True, False])
def test_growth_waits_while_the_step_found_as_many_dead_as_it_would_add(hold):
    """100 primitives, 10 of them dead: the 5% growth (5 new) waits with hold_growth, and the dead
    are relocated either way; with 2 dead (fewer than it adds) the model grows as usual."""
    for n_dead, grows in ((10, not hold), (2, True)):
        model = random_model(100, seed=5)
        with torch.no_grad():
            model.prims["opacity_logits"].fill_(math.log(0.5 / 0.5))
            model.prims["opacity_logits"][:n_dead] = -10.0  # opacity 4.5e-5 < min_opacity
        lrs = {**model.learning_rates(), "means": 1e-4}
        opt = PrimitiveAdam(model.prims, lrs)
        strategy = MCMCStrategy(MCMCConfig(refine_every=1, refine_start=0, hold_growth=hold), cap_max=1000)
        strategy.step(1, 0.0, model, opt, means_lr=1e-4, generator=torch.Generator().manual_seed(0))
        assert strategy.last_stats["relocated"] == n_dead
        assert model.num_primitives == (105 if grows else 100), (n_dead, hold)
        assert strategy.last_stats["growth_held"] == (not grows)
        assert bool((model.opacities > strategy.cfg.min_opacity).all())
