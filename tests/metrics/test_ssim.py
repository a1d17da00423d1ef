"""SSIM against a float64 direct 2-D window implementation (3DGS zero-padding convention)."""
import numpy as np
import pytest
import torch

from splatk.metrics import ssim
from splatk.metrics.ssim import C1, C2

# float32 loses ~1e-6 in E[x^2] - mu^2; measured max error ~2e-6 on these sizes.
TOL = {torch.float32: 2e-5, torch.float64: 1e-10}


def ssim_direct(x, y, window_size=11, sigma=1.5, padding="same"):
    """Straightforward SSIM: x, y [H, W, C] float64 numpy; 2-D Gaussian window at every pixel."""
    r = window_size // 2
    t = np.arange(window_size) - r
    w = np.exp(-(t[:, None] ** 2 + t[None, :] ** 2) / (2 * sigma**2))
    w /= w.sum()
    if padding == "same":  # zero padding as conv2d(padding=window // 2) in 3DGS
        x = np.pad(x, ((r, r), (r, r), (0, 0)))
        y = np.pad(y, ((r, r), (r, r), (0, 0)))
    h, wd = x.shape[0] - 2 * r, x.shape[1] - 2 * r
    out = np.empty((h, wd, x.shape[2]))
    for i in range(h):
        for j in range(wd):
            px = x[i:i + window_size, j:j + window_size]
            py = y[i:i + window_size, j:j + window_size]
            mx = np.einsum("ij,ijc->c", w, px)
            my = np.einsum("ij,ijc->c", w, py)
            vx = np.einsum("ij,ijc->c", w, (px - mx) ** 2)
            vy = np.einsum("ij,ijc->c", w, (py - my) ** 2)
            cxy = np.einsum("ij,ijc->c", w, (px - mx) * (py - my))
            out[i, j] = ((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx**2 + my**2 + C1) * (vx + vy + C2))
    return out.mean()


def _pair(h, w, seed):
    rng = np.random.default_rng(seed)
    ref = rng.uniform(0, 1, (h, w, 3))
    img = np.clip(ref + rng.normal(0, 0.15, ref.shape), 0, 1)
    # a smooth region, so the map is not all near zero
    img[: h // 2] = ref[: h // 2] * 0.9 + 0.05
    return img, ref


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("h,w", [(16, 16), (23, 37), (40, 29), (12, 64)])
@pytest.mark.parametrize("padding", ["same", "valid"])
def test_matches_direct_reference(dtype, h, w, padding):
    img, ref = _pair(h, w, seed=h * 100 + w)
    want = ssim_direct(img, ref, padding=padding)
    got = ssim(torch.from_numpy(img).to(dtype), torch.from_numpy(ref).to(dtype), padding=padding)
    assert got.shape == ()
    assert got.item() == pytest.approx(want, abs=TOL[dtype])


def test_other_window_and_batch_layout():
    img, ref = _pair(20, 24, seed=3)
    img2, ref2 = _pair(20, 24, seed=4)
    want = [ssim_direct(img, ref, 7, 1.0), ssim_direct(img2, ref2, 7, 1.0)]
    x = torch.from_numpy(np.stack([img, img2])).permute(0, 3, 1, 2)
    y = torch.from_numpy(np.stack([ref, ref2])).permute(0, 3, 1, 2)
    got = ssim(x, y, window_size=7, sigma=1.0)
    assert got.shape == (2,)
    np.testing.assert_allclose(got.numpy(), want, atol=TOL[torch.float64])


def test_identical_is_one():
    x = torch.rand(2, 3, 30, 41)
    np.testing.assert_allclose(ssim(x, x).numpy(), 1.0, atol=1e-6)
    assert ssim(x[0].permute(1, 2, 0), x[0].permute(1, 2, 0)).item() == pytest.approx(1.0, abs=1e-6)


def test_same_is_lower_than_valid_on_textured_borders():
    # zero padding scores border windows against zeros; documented in splatk.metrics.ssim
    img, ref = _pair(32, 32, seed=5)
    x, y = torch.from_numpy(img), torch.from_numpy(ref)
    assert ssim(x, y, padding="same").item() != pytest.approx(ssim(x, y, padding="valid").item(), abs=1e-4)


def test_even_window_rejected():
    with pytest.raises(ValueError, match="odd"):
        ssim(torch.rand(16, 16, 3), torch.rand(16, 16, 3), window_size=10)


def test_skimage_agrees_in_valid_mode():
    skm = pytest.importorskip("skimage.metrics")
    img, ref = _pair(40, 50, seed=6)
    # skimage's gaussian-weighted SSIM averages only the full-window ("valid") region, and
    # truncates its Gaussian at 3.5 sigma -> 11 taps for sigma 1.5, so it matches "valid",
    # not the 3DGS "same" number we report.
    want = skm.structural_similarity(img, ref, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False, data_range=1, channel_axis=2)
    got = ssim(torch.from_numpy(img), torch.from_numpy(ref), padding="valid").item()
    assert got == pytest.approx(want, abs=1e-6)


def test_gradient_flows():
    x = torch.rand(1, 3, 24, 24, requires_grad=True)
    y = torch.rand(1, 3, 24, 24)
    (1 - ssim(x, y).mean()).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


@pytest.mark.gradcheck
@pytest.mark.parametrize("window_size,sigma", [(5, 1.0), (11, 1.5)])
def test_gradcheck(window_size, sigma):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 2, 9, 12, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 2, 9, 12, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ssim(a, b, window_size, sigma), (x, y))
