"""`splatk image`: learned planar kernel table vs exact decoder, byte accounting, short fits, CLI."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk.functional.planar import bilinear
from splatk.errors import InputError
from splatk.image.bytes import (SHARED_BYTES_PER_FLOAT, SHARED_DTYPE, bytes_per_primitive, floats_per_primitive,
                                num_primitives)
from splatk.image.fit import ImageFitConfig, fit_image
from splatk.image.kernels import GABSPLAT_TOP, KERNELS, LATENT_DIM, PlanarDecoder, decoder_floats
from splatk.image.model import Splats2D, kmeans
from tests.scenes import synthetic_photo as _synthetic


def _learned(n=5, grid=8, seed=0):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)  # the decoder's init draws on the global generator
    m = Splats2D("learned", n, 16, 16, grid=grid, generator=gen)
    with torch.no_grad():  # a non-trivial decoder (the init is the constant 1)
        for p in m.decoder.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=gen))
        m.latents.normal_(0.0, 1.0, generator=gen)
    return m


def test_table_exact_at_nodes():
    m = _learned()
    table = m.kernel_table()
    g = torch.linspace(-1, 1, m.grid)
    vv, uu = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack([uu, vv], -1).reshape(-1, 2)
    for i in range(m.n):
        idx = torch.full((uv.shape[0],), i, dtype=torch.long)
        exact = m.decoder(m.turned_uv(uv, m.turns()[idx]), m.latents[idx])
        # float32 round-off only
        torch.testing.assert_close(bilinear(table, idx, uv), exact, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("grid", [4, 8])
def test_table_vs_exact_bounded(grid):
    """Between nodes the error is bounded by h^2/8 * max|second derivative| (piecewise linear MLP:
    the bound is loose, so compare against the table's own value range instead)."""
    m = _learned(grid=grid)
    table = m.kernel_table()
    gen = torch.Generator().manual_seed(1)
    uv = torch.rand(4000, 2, generator=gen) * 2 - 1
    idx = torch.randint(0, m.n, (4000,), generator=gen)
    exact = m.decoder(m.turned_uv(uv, m.turns()[idx]), m.latents[idx])
    approx = bilinear(table, idx, uv)
    err = (approx - exact).abs().detach()
    spread = float((table.max() - table.min()).detach())
    # measured: max err / spread ~0.05 (8x8) and ~0.15 (4x4) for this random decoder
    assert float(err.max().detach()) <= (0.12 if grid == 8 else 0.3) * spread
    finer = Splats2D("learned", m.n, 16, 16, grid=4 * grid)
    finer.load_state_dict(m.state_dict())
    finer.grid = 4 * grid
    err_fine = (bilinear(finer.kernel_table(), idx, uv) - exact).abs()
    assert float(err_fine.mean().detach()) < float(err.mean())  # converges as the grid refines


def test_turn_is_one_byte_and_turns_the_shape():
    """A learned splat's turn is stored in one byte (a multiple of 2 pi / 256), trains through the
    rounding, and turns the shape: a half turn draws the shape point-mirrored about the mean."""
    m = _learned(n=1)
    m.exact = True
    m.backend = "torch"
    with torch.no_grad():
        m.turn.fill_(0.3)
        m.xy_raw.zero_()  # the splat in the middle of the 16 x 16 image
        m.chol.copy_(torch.tensor([[2.5, 0.4, 1.5]]))
    step = 2 * math.pi / 256
    stored = float(m.turns().detach()[0])
    assert abs(stored / step - round(stored / step)) < 1e-5 and abs(stored - 0.3) <= step / 2
    img = m.render()
    img.sum().backward()
    assert m.turn.grad is not None and float(m.turn.grad.abs().sum()) > 0
    with torch.no_grad():
        # the kernel at (u, v) with a half turn is the kernel at (-u, -v) without it
        uv = torch.rand(50, 2, generator=torch.Generator().manual_seed(2)) * 1.4 - 0.7
        idx = torch.zeros(50, dtype=torch.long)
        k0 = m.kernel_values(-uv, idx)
        m.turn.add_(math.pi)
        torch.testing.assert_close(m.kernel_values(uv, idx), k0, atol=1e-5, rtol=1e-4)
        assert float((k0 - m.kernel_values(-uv, idx)).abs().max()) > 1e-3  # the shape is not symmetric


@torch.no_grad()
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_render_table_matches_exact_mode(seed):
    """The table render approaches the exact one as the table refines. Over 40 random decoders
    the 8x8 table's largest pixel error was up to 0.27 of the image's largest value, and a 32x32
    table cut it to at most 0.42 of the 8x8's."""
    m = _learned(n=6, seed=seed)
    m.exact = True
    exact = m.render()
    m.exact = False
    err8 = float((m.render() - exact).abs().max())
    m.grid = 32
    err32 = float((m.render() - exact).abs().max())
    assert err8 <= 0.3 * float(exact.abs().max()) + 1e-6
    assert err32 <= 0.5 * err8


@pytest.mark.parametrize("kernel,latent_dim", [(k, 2) for k in KERNELS] + [("learned", 0), ("learned", 10)])
@pytest.mark.parametrize("budget", [1000, 8192, 65536])
def test_bytes_within_budget(kernel, latent_dim, budget):
    n = num_primitives(kernel, budget, latent_dim)
    m = Splats2D(kernel, max(n, 1), 8, 8, latent_dim=latent_dim)
    # every per-primitive parameter is counted: floats at 4 bytes, the learned kernel's turn at one;
    # GabSplat trains a coefficient per bank frequency and stores the top K per axis, each with a
    # one-byte bank index
    stored = {"wave_coeffs": 2 * GABSPLAT_TOP * m.n}
    per_prim = sum(stored.get(name, p.numel()) for name, p in m.named_parameters()
                   if not name.startswith("decoder.") and name != "turn") // m.n
    assert per_prim == floats_per_primitive(kernel, latent_dim)
    per_bytes = 4 * per_prim + {"learned": 1, "gabsplat": 2 * GABSPLAT_TOP}.get(kernel, 0)
    assert per_bytes == bytes_per_primitive(kernel, latent_dim)
    # the shared decoder is stored at float16 and paid from the same budget (but for the paper's
    # kernel, whose budget counts the primitives only)
    net = SHARED_BYTES_PER_FLOAT * decoder_floats(latent_dim) if kernel.startswith("learned") else 0
    paid = net if kernel == "learned" else 0
    assert n * per_bytes + paid <= budget < (n + 1) * per_bytes + paid
    assert m.describe_bytes()["bytes"] == m.n * per_bytes + net
    assert m.describe_bytes()["counted_bytes"] == m.n * per_bytes + paid
    if kernel == "learned":
        assert per_prim == 8 + latent_dim
        assert decoder_floats(latent_dim) == sum(p.numel() for p in PlanarDecoder(latent_dim).parameters())
        assert m.describe_bytes()["network_bytes"] == 2 * decoder_floats(latent_dim)


def test_latent_dim_must_not_be_negative():
    with pytest.raises(InputError):
        fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=4000, iters=0, latent_dim=-1))


@pytest.mark.parametrize("kernel", KERNELS)
def test_short_fit_raises_psnr(kernel):
    torch.set_num_threads(1)
    target = _synthetic()
    cfg0 = ImageFitConfig(kernel=kernel, budget_bytes=40 * 4 * floats_per_primitive(kernel), iters=0)
    m0, _ = fit_image(target, cfg0)
    cfg = ImageFitConfig(kernel=kernel, budget_bytes=cfg0.budget_bytes, iters=60)
    m1, _ = fit_image(target, cfg)

    def psnr(m):
        with torch.no_grad():
            return -10 * math.log10(float(((m.render().clamp(0, 1) - target) ** 2).mean()))

    assert psnr(m1) > psnr(m0) + 5.0


def test_cli_writes_metrics(tmp_path):
    from PIL import Image
    from splatk_cli.main import cli

    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(32, 48).numpy() * 255).astype(np.uint8)).save(photo)
    out = tmp_path / "run"
    args = ["image", str(photo), "--kernel", "learned", "--budget-bytes", "2000", "--out", str(out),
            "--iters", "5", "--downscale", "2", "--threads", "1", "-q", "--no-lpips"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "lpips", "bytes", "num_primitives", "kernel", "iterations", "seconds"):
        assert key in m
    assert m["kernel"] == "learned" and m["iterations"] == 5
    # the default learned kernel draws from a palette: decoder and palette paid once, a byte per splat
    shapes = ImageFitConfig().shapes
    assert m["shapes"] == shapes > 0
    net = 2 * (decoder_floats() + shapes * LATENT_DIM)  # float16
    # a byte for the palette index and one for the turn
    n = (2000 - net) // (4 * 8 + 2)
    assert m["num_primitives"] == n and m["bytes"] <= 2000
    assert m["bytes"] == m["primitive_bytes"] + m["network_bytes"]
    # k-means makes at most one shape per splat, and bytes counts the palette made
    assert n < shapes and m["network_bytes"] == 2 * (decoder_floats() + n * LATENT_DIM)
    assert m["latent_dim"] == LATENT_DIM and m["config"]["latent_dim"] == LATENT_DIM
    assert Image.open(out / "render.png").size == (24, 16)
    assert (out / "primitives.png").is_file() and (out / "kernels.png").is_file()
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 2 and "overwrite" in again.output


def test_cli_latent_dim_recorded(tmp_path):
    from PIL import Image
    from splatk_cli.main import cli

    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(32, 48).numpy() * 255).astype(np.uint8)).save(photo)
    out = tmp_path / "run"
    args = ["image", str(photo), "--kernel", "learned", "--budget-bytes", "2000", "--out", str(out),
            "--latent-dim", "3", "--shapes", "0", "--iters", "2", "--downscale", "2", "--threads", "1", "-q",
            "--no-lpips"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["latent_dim"] == 3 and m["config"]["latent_dim"] == 3
    assert m["bytes_per_primitive"] == 4 * (8 + 3) + 1  # the latent's floats and the turn's byte
    assert m["num_primitives"] == (2000 - 2 * decoder_floats(3)) // 45
    assert m["network_bytes"] == 2 * decoder_floats(3) and m["network_floats"] == decoder_floats(3)
    assert m["shapes"] == 0


def test_cli_reads_byte_sizes_with_units(tmp_path):
    from PIL import Image
    from splatk_cli.main import cli

    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(32, 48).numpy() * 255).astype(np.uint8)).save(photo)
    base = ["image", str(photo), "--kernel", "gaussian", "--iters", "2", "--downscale", "2", "--threads", "1",
            "-q", "--no-lpips"]
    res = CliRunner().invoke(cli, base + ["--budget-bytes", "1KB", "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "a" / "metrics.json").read_text())["num_primitives"] == 1024 // 32
    bad = CliRunner().invoke(cli, base + ["--budget-bytes", "lots", "--out", str(tmp_path / "b")])
    assert bad.exit_code == 2 and "byte size" in bad.output


def test_cli_backends_agree_and_exact_refuses_cpu(tmp_path):
    """--backend torch and cpu fit the same splats (the native op is the torch path's twin), and the
    exact learned mode, which only the torch path has, is refused on cpu with a clear message."""
    from PIL import Image
    from splatk.backends.cpu_native import available
    from splatk_cli.main import cli

    if not available():
        pytest.skip("native cpu backend unavailable")
    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(32, 48).numpy() * 255).astype(np.uint8)).save(photo)
    base = ["image", str(photo), "--kernel", "learned", "--budget-bytes", "2000", "--iters", "20",
            "--threads", "1", "-q", "--no-lpips"]
    psnrs = {}
    for backend in ("torch", "cpu"):
        res = CliRunner().invoke(cli, base + ["--backend", backend, "--out", str(tmp_path / backend)])
        assert res.exit_code == 0, res.output
        m = json.loads((tmp_path / backend / "metrics.json").read_text())
        assert m["config"]["backend"] == backend
        psnrs[backend] = m["psnr"]
    assert abs(psnrs["torch"] - psnrs["cpu"]) < 0.05
    bad = CliRunner().invoke(cli, base + ["--backend", "cpu", "--exact", "--out", str(tmp_path / "x")])
    assert bad.exit_code != 0 and "exact" in bad.output and "Traceback" not in bad.output


@pytest.mark.parametrize("shapes", [0, 64])
def test_budget_below_one_primitive_says_what_it_needs(shapes):
    """A budget that cannot pay for the decoder (and palette) plus one primitive is an input error
    naming the smallest budget that works, and that budget fits exactly one primitive."""
    needs = 2 * decoder_floats() + 2 * shapes * LATENT_DIM + bytes_per_primitive("learned", LATENT_DIM, shapes)
    with pytest.raises(InputError, match=f"at least {needs}"):
        fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=needs - 1, iters=0, shapes=shapes))
    model, summary = fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=needs, iters=0,
                                                            shapes=shapes))
    assert summary["num_primitives"] == 1


# ---- the shape palette (a learned kernel with K shared latents, one byte per splat) -------------

def test_kmeans_finds_separated_clusters():
    gen = torch.Generator().manual_seed(3)
    centres = torch.tensor([[0.0, 0.0], [5.0, 5.0], [-5.0, 5.0]])
    labels_true = torch.arange(300) % 3
    pts = centres[labels_true] + 0.1 * torch.randn(300, 2, generator=gen)
    got, labels = kmeans(pts, 3, torch.Generator().manual_seed(0))
    # every true cluster maps to one found centre, within its spread
    for j in range(3):
        assert labels[labels_true == j].unique().numel() == 1
        assert float((got[labels[labels_true == j][0]] - centres[j]).norm()) < 0.05
    # more clusters than points: one centre per point
    c2, l2 = kmeans(pts[:2], 8, torch.Generator().manual_seed(0))
    assert c2.shape[0] == 2 and sorted(l2.tolist()) == [0, 1]
    # one cluster: the mean, and the points are left as they were
    before = pts.clone()
    c1, l1 = kmeans(pts, 1)
    torch.testing.assert_close(c1[0], before.mean(0))
    assert torch.equal(pts, before) and l1.unique().tolist() == [0]


@pytest.mark.parametrize("shapes", [1, 16, 256])
@pytest.mark.parametrize("budget", [4000, 24576])
def test_palette_bytes_within_budget(shapes, budget):
    n = num_primitives("learned", budget, 2, shapes)
    per = bytes_per_primitive("learned", 2, shapes)
    assert per == 4 * 8 + 2  # geometry and colour at float32, the palette index and the turn a byte each
    net = 2 * (decoder_floats(2) + shapes * 2)  # the decoder and the palette, paid once at float16
    assert n * per + net <= budget < (n + 1) * per + net
    m = Splats2D("learned", max(n, 1), 8, 8, shapes=shapes)
    m.quantize_shapes(torch.Generator().manual_seed(0))
    assert m.palette.shape[0] == min(shapes, m.n) and m.shape_index.max() < m.palette.shape[0]
    # bytes counts the palette made: k-means makes at most one shape per splat
    assert m.describe_bytes()["bytes"] == m.n * per + 2 * (decoder_floats(2) + m.palette.shape[0] * 2) <= budget
    with pytest.raises(ValueError, match="shapes"):
        num_primitives("learned", budget, 2, 257)


def test_fit_stores_the_shared_decoder_and_palette_at_their_paid_precision():
    """network_bytes pays float16 for the decoder and palette, so the fitted model must hold
    values that float16 represents exactly (the image measured is the image stored), while the
    per-splat values stay float32 (a float16 round trip changes some of them)."""
    torch.set_num_threads(1)
    assert SHARED_BYTES_PER_FLOAT == torch.finfo(SHARED_DTYPE).bits // 8
    m, _ = fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=3000, iters=12, shapes=8,
                                                  shape_start=0.5))
    shared = list(m.decoder.parameters()) + [m.palette]
    for p in shared:
        torch.testing.assert_close(p.detach(), p.detach().to(SHARED_DTYPE).float(), atol=0, rtol=0)
    colors = m.colors.detach()
    assert not torch.equal(colors, colors.to(SHARED_DTYPE).float())


def test_palette_draws_each_splat_with_its_entry():
    """After quantize_shapes every splat draws with its palette latent: the table, the exact
    decoder and both backends agree, and the palette gets the gradient (the latents do not)."""
    m = _learned(n=12)
    m.shapes = 3
    m.quantize_shapes(torch.Generator().manual_seed(0))
    lat = m.splat_latents()
    assert torch.equal(lat, m.palette[m.shape_index])
    assert m.shape_index.unique().numel() == 3
    table = m.kernel_table()
    g = torch.linspace(-1.0, 1.0, m.grid)
    vv, uu = torch.meshgrid(g, g, indexing="ij")
    uv = torch.stack([uu, vv], -1).reshape(1, -1, 2)
    ref = m.decoder(m.turned_uv(uv, m.turns()[:, None]), lat[:, None, :]).reshape(m.n, m.grid, m.grid)
    torch.testing.assert_close(table, ref)
    m.backend = "torch"
    a = m.render()
    m.exact = True
    b = m.render().detach()
    assert float((a.detach() - b).abs().max()) <= 0.1 * float(b.abs().max()) + 1e-6
    m.exact = False
    from splatk.backends.cpu_native import available
    if available():
        m.backend = "cpu"
        torch.testing.assert_close(m.render(), a, atol=1e-5, rtol=1e-4)
    a.sum().backward()
    assert m.palette.grad is not None and float(m.palette.grad.abs().sum()) > 0
    assert m.latents.grad is None


def test_palette_fit_raises_psnr_and_records_shapes(tmp_path):
    torch.set_num_threads(1)
    target = _synthetic()
    budget = 2 * decoder_floats(2) + 2 * 16 * 2 + 40 * bytes_per_primitive("learned", 2, 16)
    m0, _ = fit_image(target, ImageFitConfig(kernel="learned", budget_bytes=budget, iters=0, shapes=16))
    m1, summary = fit_image(target, ImageFitConfig(kernel="learned", budget_bytes=budget, iters=80, shapes=16))
    assert summary["num_primitives"] == 40 and m1.palette is not None

    def psnr(m):
        with torch.no_grad():
            return -10 * math.log10(float(((m.render().clamp(0, 1) - target) ** 2).mean()))

    assert psnr(m1) > psnr(m0) + 5.0
    with pytest.raises(InputError, match="shapes"):
        fit_image(target, ImageFitConfig(kernel="learned", budget_bytes=budget, iters=0, shapes=300))
    # with no latent (one shared shape) a palette has nothing to share: none is made or paid for
    m2, _ = fit_image(target, ImageFitConfig(kernel="learned", budget_bytes=budget, iters=2, shapes=16, latent_dim=0))
    assert m2.shapes == 0 and m2.palette is None
