"""The native image-splat renderer (backends/image_cpu.py) against the torch path of
``Splats2D.render`` (the reference): same image and gradients for every 2D kernel, in float64
and float32, splats reaching outside the image included; gradcheck of the op itself."""
from __future__ import annotations

import pytest
import torch

from splatk.backends.image_cpu import render_image_splats_cpu
from splatk.image.kernels import GABOR_WAVES, IMAGE_KERNELS, KERNELS
from splatk.image.model import Splats2D


def _native_or_skip():
    from splatk.backends.cpu_native import available

    if not available():
        pytest.skip("native cpu backend unavailable")


def _splats(kernel: str, dtype=torch.float64, n: int = 60, h: int = 37, w: int = 53, seed: int = 1):
    """Splats with every kernel parameter away from its init (the learned decoder starts as the
    constant 1, which would pass no gradient to the latents), some wide, sheared and off-image."""
    gen = torch.Generator().manual_seed(seed)
    m = Splats2D(kernel, n, h, w, generator=gen)
    with torch.no_grad():
        m.xy_raw.mul_(1.6)  # tanh space: some means land near or past the border
        m.colors.normal_(0.0, 1.0, generator=gen)
        m.chol.mul_(torch.rand(m.chol.shape, generator=gen) * 2.0 + 0.3)
        m.chol[:, 1].normal_(0.0, 2.0, generator=gen)
        if kernel == "gabor":
            m.gabor_amps.normal_(0.0, 1.0, generator=gen)
            m.gabor_freqs.uniform_(0.0, 3.0, generator=gen)
        if kernel == "learned":
            m.latents.normal_(0.0, 1.0, generator=gen)
            for p in m.decoder.parameters():
                p.add_(0.5 * torch.randn(p.shape, generator=gen))
    return m.to(dtype)


def _render_and_grads(m: Splats2D, backend: str):
    m.backend = backend
    m.zero_grad()
    img = m.render()
    weight = torch.sin(torch.arange(img.numel(), dtype=img.dtype)).reshape(img.shape)
    (img * weight).sum().backward()
    return img.detach().clone(), {n: p.grad.clone() for n, p in m.named_parameters()}


NATIVE = [k for k in KERNELS if IMAGE_KERNELS[k].has_native]


@pytest.mark.parametrize("kernel", NATIVE)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_matches_torch(kernel, dtype):
    _native_or_skip()
    m = _splats(kernel, dtype)
    img_t, grads_t = _render_and_grads(m, "torch")
    img_c, grads_c = _render_and_grads(m, "cpu")
    assert img_t.abs().max() > 0.1  # the test scene draws something
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(img_c, img_t, rtol=tol, atol=tol)
    for name, g in grads_t.items():
        scale = float(g.abs().max())
        assert scale > 0, f"{name}: the test passes no gradient"
        rel = 1e-10 if dtype == torch.float64 else 2e-3
        torch.testing.assert_close(grads_c[name], g, rtol=rel, atol=rel * scale, msg=name)


def test_auto_picks_native_on_cpu():
    _native_or_skip()
    m = _splats("gaussian")
    m.backend = "auto"
    assert m.uses_native()
    m.backend = "torch"
    assert not m.uses_native()
    m = _splats("learned")
    m.exact = True
    m.backend = "cpu"
    with pytest.raises(ValueError, match="exact"):
        m.uses_native()


@pytest.mark.parametrize("kernel", [k for k in KERNELS if k not in NATIVE])
def test_kernels_without_native_op_draw_with_torch(kernel):
    """auto draws them with the torch path; an explicit cpu backend is refused naming the pair."""
    _native_or_skip()
    m = Splats2D(kernel, 5, 12, 16, generator=torch.Generator().manual_seed(0))
    m.backend = "auto"
    assert not m.uses_native()
    m.backend = "cpu"
    with pytest.raises(ValueError, match=f"{kernel} kernel has no cpu backend"):
        m.uses_native()


@pytest.mark.parametrize("kind", ["gaussian", "gabor", "table"])
def test_gradcheck_native_op(kind):
    _native_or_skip()
    gen = torch.Generator().manual_seed(3)
    n, h, w = 3, 9, 11
    means = (torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([w, h])).requires_grad_()
    chol = torch.tensor([[1.3, 0.4, 1.1], [0.9, -0.5, 1.6], [2.0, 0.2, 0.8]], dtype=torch.float64,
                        requires_grad=True)
    colors = torch.randn(n, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    if kind == "gabor":
        aux = GABOR_WAVES
        extras = torch.cat([torch.randn(n, 2 * aux, generator=gen, dtype=torch.float64),
                            torch.rand(n, 2 * aux, generator=gen, dtype=torch.float64) * 2], 1)
    elif kind == "table":
        aux = 4
        extras = torch.randn(n, aux * aux, generator=gen, dtype=torch.float64)
    else:
        aux, extras = 0, torch.zeros(n, 0, dtype=torch.float64)
    extras.requires_grad_()
    # boxes fixed (as Splats2D computes them without grad): 3 sigma around each mean, generous
    x0 = (means.detach()[:, 0] - 7).floor().int()
    y0 = (means.detach()[:, 1] - 7).floor().int()
    bbox = torch.stack([x0, y0, x0 + 15, y0 + 15], 1).to(torch.int32).contiguous()

    def f(mu, ch, col, ex):
        return render_image_splats_cpu(mu, ch, col, ex, bbox, kind, aux, w, h)

    assert torch.autograd.gradcheck(f, (means, chol, colors, extras), eps=1e-6, atol=1e-6)
