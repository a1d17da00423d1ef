"""The scale regulariser charges a primitive's footprint: a learned (1-sigma support) kernel's
scales at a third of a Gaussian's (3-sigma support) weight (decision 0102)."""
import pytest
import torch

from splatk.kernels.learned import LearnedKernel
from splatk.train.losses import regularisers
from tests.scenes import random_model


def test_the_learned_kernel_pays_a_third_per_unit_scale():
    gaussian, learned = random_model(30, 1), random_model(30, 1, kernel="learned")
    mean_scale = float(gaussian.scales.detach().abs().mean())
    assert torch.equal(gaussian.scales, learned.scales)
    assert float(regularisers(gaussian, 0.0, 0.01).detach()) == pytest.approx(0.01 * mean_scale, rel=1e-6)
    assert float(regularisers(learned, 0.0, 0.01).detach()) == pytest.approx(0.01 * mean_scale / 3, rel=1e-6)
    # the same footprint on screen (learned scales three times the Gaussian's) costs the same
    with torch.no_grad():
        learned.prims["log_scales"] += torch.log(torch.tensor(3.0))
    assert float(regularisers(learned, 0.0, 0.01).detach()) == pytest.approx(float(regularisers(gaussian, 0.0, 0.01).detach()), rel=1e-5)


def test_scale_reg_weight_is_a_recorded_checked_option():
    assert LearnedKernel().options["scale_reg_weight"] == pytest.approx(1 / 3)
    assert LearnedKernel(scale_reg_weight=1.0).scale_reg_weight == 1.0  # the paper's (DBS's) regulariser
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="scale_reg_weight"):
            LearnedKernel(scale_reg_weight=bad)
