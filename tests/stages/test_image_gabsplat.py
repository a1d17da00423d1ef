"""`splatk image --kernel gabsplat` (GabSplat) and `--mode paper` (the paper's planar kernel and
byte count): the kernel's formula and gradients, short fits, and what the budget pays for."""
from __future__ import annotations

import json
import math

import pytest
import torch
from click.testing import CliRunner

from splatk.image.bytes import bytes_per_primitive, num_primitives
from splatk.image.file import HEADER_BYTES, load_splats2d, save_splats2d
from splatk.image.fit import ImageFitConfig, fit_image
from splatk.image.kernels import (GABSPLAT_BANK, GABSPLAT_FREQ_STEP, GABSPLAT_RANDOM, GABSPLAT_TOP,
                                  PAPER_LATENT_DIM, GabSplatKernel2D, decoder_floats)
from splatk.image.model import Splats2D
from tests.scenes import synthetic_photo as _synthetic


def _psnr(img: torch.Tensor, target: torch.Tensor) -> float:
    return -10.0 * math.log10(float(((img.clamp(0, 1) - target) ** 2).mean()))


def _gabsplat(n=3, h=10, w=12, dtype=torch.float32, seed=0) -> Splats2D:
    """GabSplat splats with turned, stretched ellipses and several waves per axis."""
    gen = torch.Generator().manual_seed(seed)
    m = Splats2D("gabsplat", n, h, w, generator=gen, backend="torch").to(dtype)
    with torch.no_grad():
        m.sigmas.copy_(torch.rand(n, 2, generator=gen, dtype=dtype) * 2.0 + 1.0)
        m.angle.uniform_(0.0, math.pi, generator=gen)
        m.colors.uniform_(-1.0, 1.0, generator=gen)
        # distinct magnitudes, so a small step never reorders the top K
        mags = torch.linspace(1.0, 0.05, GABSPLAT_BANK, dtype=dtype)
        perm = torch.stack([torch.randperm(GABSPLAT_BANK, generator=gen) for _ in range(2 * n)]).reshape(n, 2, -1)
        signs = torch.where(torch.rand(n, 2, GABSPLAT_BANK, generator=gen) < 0.5, -1.0, 1.0).to(dtype)
        m.wave_coeffs.copy_(mags[perm] * signs)
    return m


def test_gabsplat_render_is_the_rotation_scale_formula():
    """The sum over pixels of GabSplat's kernel, written from its definition (peers.md 7.3)."""
    m = _gabsplat(n=2, h=20, w=24, dtype=torch.float64)
    with torch.no_grad():
        m.sigmas.copy_(torch.tensor([[2.0, 1.2], [1.5, 2.5]], dtype=torch.float64))
        img = m.render()
        f64 = torch.float64
        ys, xs = torch.meshgrid(torch.arange(m.height, dtype=f64) + 0.5, torch.arange(m.width, dtype=f64) + 0.5,
                                indexing="ij")
        means = m.means_px()
        top = GabSplatKernel2D.top(m)
        want = torch.zeros_like(img)
        for i in range(m.n):
            s1, s2 = float(m.sigmas[i, 0]) + 0.3, float(m.sigmas[i, 1]) + 0.3
            c, s = math.cos(float(m.angle[i])), math.sin(float(m.angle[i]))
            dx, dy = xs - means[i, 0], ys - means[i, 1]
            t = [(c * dx + s * dy) / s1, (-s * dx + c * dy) / s2]
            r2 = t[0] ** 2 + t[1] ** 2
            k = torch.exp(-0.5 * r2) * (r2 <= 9.0)  # cut at 3 sigma
            for d in range(2):
                waves = sum(m.wave_coeffs[i, d, j] * torch.cos(j * GABSPLAT_FREQ_STEP * t[d])
                            for j in top[i, d].tolist())
                k = k * waves
            want += k[..., None] * m.colors[i]
    torch.testing.assert_close(img, want, atol=1e-10, rtol=1e-9)


@pytest.mark.gradcheck
def test_gabsplat_gradcheck():
    torch.manual_seed(0)
    m = _gabsplat(n=3, dtype=torch.float64)
    m.kernel2d.before_step(m, 0.0, torch.Generator().manual_seed(1))  # top K and random picks
    assert m.wave_random.shape == (3, 2, GABSPLAT_RANDOM)
    names = ["xy_raw", "sigmas", "angle", "colors", "wave_coeffs"]
    start = [getattr(m, name).detach().clone() for name in names]
    for name in names:  # plain tensors from here, so gradcheck's inputs are what renders
        del m._parameters[name]

    def render(*values):
        for name, v in zip(names, values):
            setattr(m, name, v)
        return m.render()

    inputs = [v.requires_grad_(True) for v in start]
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6)


def test_gabsplat_fit_reaches_psnr_and_its_file_redraws_it(tmp_path):
    torch.set_num_threads(1)
    target = _synthetic(32, 48)
    cfg = ImageFitConfig(kernel="gabsplat", budget_bytes=2048, iters=150, lpips=False)
    model, summary = fit_image(target, cfg)
    assert summary["num_primitives"] == 2048 // bytes_per_primitive("gabsplat") == 2048 // 52
    with torch.no_grad():
        img = model.render()
    assert _psnr(img, target) > 24.0
    # the waves moved off the Gaussian they started as
    top = GabSplatKernel2D.top(model)
    assert (top != 0).any() and model.wave_coeffs.gather(2, top)[..., 1:].abs().max() > 0.05
    path = save_splats2d(model, tmp_path / "splats.bin")
    assert path.stat().st_size == HEADER_BYTES + summary["num_primitives"] * (4 * (8 + 2 * GABSPLAT_TOP)
                                                                               + 2 * GABSPLAT_TOP)
    with torch.no_grad():
        torch.testing.assert_close(load_splats2d(path).render(), img, atol=0, rtol=0)


@pytest.mark.parametrize("budget", [2048, 8192, 24576])
def test_paper_mode_counts_the_primitives_as_the_paper(budget):
    """Paper mode: 18 float32 per splat (xy 2, Cholesky 3, colour 3, latent 10); the decoder is
    stored (float16) but the budget does not pay for it."""
    torch.set_num_threads(1)
    per = 4 * (2 + 3 + 3 + PAPER_LATENT_DIM)
    model, summary = fit_image(_synthetic(), ImageFitConfig(kernel="learned", mode="paper", budget_bytes=budget,
                                                            iters=1, lpips=False))
    n = budget // per
    assert (model.kernel, model.latent_dim, summary["num_primitives"]) == ("learned-paper", PAPER_LATENT_DIM, n)
    sizes = model.describe_bytes()
    assert sizes["counted_bytes"] == n * per <= budget
    assert sizes["bytes"] == n * per + 2 * decoder_floats(PAPER_LATENT_DIM)
    assert num_primitives("learned-paper", budget, PAPER_LATENT_DIM) == n
    # tuned mode pays for its decoder and palette out of the same budget
    tuned, _ = fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=budget, iters=1, lpips=False))
    assert tuned.describe_bytes()["counted_bytes"] == tuned.describe_bytes()["bytes"] <= budget


def test_paper_kernel_starts_as_the_gaussian_surfel():
    """The paper pretrains the planar decoder on 2D Gaussian surfels; latents start at zero."""
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    m = Splats2D("learned-paper", 4, 16, 16, generator=gen, latent_dim=PAPER_LATENT_DIM, exact=True, backend="torch")
    m.kernel2d.prepare(m, gen)
    uv = torch.rand(500, 2, generator=gen) * 2 - 1
    uv = uv[(uv * uv).sum(-1) <= 1.0]
    with torch.no_grad():
        k = m.kernel_values(uv, torch.zeros(uv.shape[0], dtype=torch.long))
    err = (k - torch.exp(-4.5 * (uv * uv).sum(-1))).abs()
    # 300 Adam steps of an 8-wide decoder: mean 0.01 and worst 0.07 seen here
    assert err.mean() < 0.02 and err.max() < 0.1
    with torch.no_grad():  # outside the unit disk: nothing, whatever the decoder says there
        assert float(m.kernel_values(torch.tensor([[1.0, 0.5]]), torch.zeros(1, dtype=torch.long))) == 0.0


def test_paper_mode_fit_and_cli(tmp_path):
    from splatk_cli.main import cli
    from PIL import Image
    import numpy as np

    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(24, 32).numpy() * 255).astype(np.uint8)).save(photo)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["image", str(photo), "--mode", "paper", "--budget-bytes", "1440", "--iters", "60",
                                   "--out", str(out), "--no-lpips", "--quiet", "--threads", "1"])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert (m["kernel"], m["mode"], m["num_primitives"], m["counted_bytes"]) == ("learned-paper", "paper", 20, 1440)
    assert m["file_bytes"] == HEADER_BYTES + m["bytes"] == HEADER_BYTES + 1440 + 2 * decoder_floats(PAPER_LATENT_DIM)
    assert m["psnr"] > 18.0
    bad = CliRunner().invoke(cli, ["image", str(photo), "--mode", "exact", "--out", str(tmp_path / "o2")])
    assert bad.exit_code == 2 and "--mode" in bad.output
