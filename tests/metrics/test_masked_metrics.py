"""Masked pixels (a dataset's masks) do not count in PSNR, SSIM or LPIPS."""
from __future__ import annotations

import pytest
import torch

from splatk.metrics import compute_metrics, lpips_available, psnr, ssim


def _pair(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(32, 40, 3, generator=g)
    img = (ref + 0.05 * torch.randn(32, 40, 3, generator=g)).clamp(0, 1)
    mask = torch.ones(32, 40, 1)
    mask[:, :10] = 0
    return img, ref, mask


def _scribbled(x: torch.Tensor, seed: int) -> torch.Tensor:
    out = x.clone()
    out[:, :10] = torch.rand(32, 10, 3, generator=torch.Generator().manual_seed(seed))
    return out


def test_psnr_and_ssim_ignore_masked_pixels():
    img, ref, mask = _pair()
    for metric in (psnr, ssim):
        value = metric(img, ref, mask=mask)
        assert torch.allclose(metric(_scribbled(img, 1), _scribbled(ref, 2), mask=mask), value), metric
        assert not torch.allclose(metric(_scribbled(img, 1), _scribbled(ref, 2)), metric(img, ref)), metric


def test_psnr_is_the_mse_over_the_kept_pixels():
    img, ref, mask = _pair()
    mse = ((img - ref) ** 2)[:, 10:].mean()
    assert float(psnr(img, ref, mask=mask)) == pytest.approx(float(-10 * torch.log10(mse)), rel=1e-5)
    assert torch.equal(psnr(img, ref, mask=torch.ones(32, 40, 1)), psnr(img, ref))


def test_ssim_mask_in_a_batch_and_valid_padding():
    img, ref, mask = _pair()
    batch = lambda x: x.permute(2, 0, 1)[None]  # noqa: E731
    one = ssim(img, ref, mask=mask)
    assert torch.allclose(ssim(batch(img), batch(ref), mask=batch(mask))[0], one)
    valid = ssim(img, ref, padding="valid", mask=mask)
    assert torch.allclose(ssim(_scribbled(img, 3), _scribbled(ref, 4), padding="valid", mask=mask), valid)


def test_compute_metrics_with_a_mask():
    img, ref, mask = _pair()
    names = ("psnr", "ssim", "lpips") if lpips_available("alex") else ("psnr", "ssim")
    a = compute_metrics(img, ref, names, mask=mask)
    b = compute_metrics(_scribbled(img, 5), _scribbled(ref, 6), names, mask=mask)
    for name in names:
        assert a[name] == pytest.approx(b[name], abs=1e-6), name
