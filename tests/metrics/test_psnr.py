"""PSNR against its closed form."""
import math

import numpy as np
import pytest
import torch

from splatk.metrics import psnr

# Tolerances in dB per dtype. float32: MSE of ~1e5 terms in float32, relative error ~1e-6.
TOL = {torch.float32: 1e-4, torch.float64: 1e-10}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.01, 0.05, 0.1])
def test_sign_noise_matches_closed_form(dtype, sigma):
    # ref in [0.25, 0.75] and noise +-sigma: no clamping, MSE = sigma^2 exactly.
    g = torch.Generator().manual_seed(0)
    ref = 0.25 + 0.5 * torch.rand(48, 64, 3, generator=g, dtype=torch.float64)
    signs = torch.randint(0, 2, ref.shape, generator=g).to(torch.float64) * 2 - 1
    img = ref + sigma * signs
    got = psnr(img.to(dtype), ref.to(dtype))
    assert got.shape == ()
    assert got.item() == pytest.approx(-20 * math.log10(sigma), abs=TOL[dtype])


def test_gaussian_noise_matches_numpy():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.3, 0.7, (2, 3, 20, 30))
    img = np.clip(ref + rng.normal(0, 0.03, ref.shape), 0, 1)
    got = psnr(torch.from_numpy(img), torch.from_numpy(ref))
    want = [-10 * np.log10(np.mean((img[b] - ref[b]) ** 2)) for b in range(2)]
    assert got.shape == (2,)
    np.testing.assert_allclose(got.numpy(), want, atol=TOL[torch.float64])


def test_identical_is_inf_and_img_is_clamped():
    ref = torch.rand(16, 16, 3)
    assert math.isinf(psnr(ref, ref).item())
    ref[0, 0] = 1.0
    img = ref.clone()
    img[0, 0] = 1.7  # an overshooting render: clamped to the reference's 1.0
    assert math.isinf(psnr(img, ref).item())


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match="differs"):
        psnr(torch.rand(8, 8, 3), torch.rand(8, 9, 3))
