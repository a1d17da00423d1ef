"""Learned planar kernel: table vs exact decoder, the dense planar rasteriser, pretraining."""
from __future__ import annotations

import json
import math

import torch

from splatk.backends.planar_torch import rasterize_planar
from splatk.functional.planar import gaussian_surfel
from splatk.kernels.learned_planar import LearnedPlanarKernel


def _kernel_and_latents(grid=8, m=6):
    torch.manual_seed(0)
    k = LearnedPlanarKernel(grid=grid)
    gen = torch.Generator().manual_seed(1)
    z = torch.randn(m, k.latent_dim, generator=gen)
    means = torch.randn(m, 3, generator=gen) + torch.tensor([0.0, 0.0, 5.0])
    scales = torch.rand(m, 2, generator=gen) * 0.3 + 0.05
    rot = torch.linalg.qr(torch.randn(m, 3, 3, generator=gen))[0]
    return k, k.project(z, means, scales, rot).detach()


@torch.no_grad()
def test_table_exact_at_nodes_and_bounded_between():
    k, za = _kernel_and_latents()
    table = k.table(za)
    nodes = k.nodes()
    for i in range(za.shape[0]):
        idx = torch.full((nodes.shape[0],), i, dtype=torch.long)
        inside = (nodes * nodes).sum(-1) <= 1.0
        torch.testing.assert_close(k.lookup(table, nodes, idx)[inside], k.exact(nodes, idx, za)[inside],
                                   atol=1e-5, rtol=1e-5)  # float32 round-off
    gen = torch.Generator().manual_seed(2)
    uv = torch.rand(5000, 2, generator=gen) * 2 - 1
    idx = torch.randint(0, za.shape[0], (5000,), generator=gen)
    err = (k.lookup(table, uv, idx) - k.exact(uv, idx, za)).abs()
    # sigmoid outputs in (0, 1); measured max error ~0.02 on an 8x8 grid for He-init networks
    assert float(err.max()) < 0.08
    fine = LearnedPlanarKernel(grid=32)
    fine.load_state_dict(k.state_dict())
    err_fine = (fine.lookup(fine.table(za), uv, idx) - k.exact(uv, idx, za)).abs()
    assert float(err_fine.mean()) < float(err.mean())


def test_rasterize_planar_fronto_parallel_disk():
    """One disk facing the camera: alpha at each pixel is o * exp(-r^2 / 2) with r in sigmas."""
    dt = torch.float64
    f, z, s = 100.0, 4.0, 0.2
    K = torch.tensor([[f, 0, 16.0], [0, f, 16.0], [0, 0, 1]], dtype=dt)
    out = rasterize_planar(torch.tensor([[0.0, 0.0, z]], dtype=dt), torch.tensor([[1.0, 0, 0, 0]], dtype=dt),
                           torch.tensor([[s, s]], dtype=dt), torch.tensor([0.8], dtype=dt),
                           torch.ones(1, 3, dtype=dt), torch.eye(4, dtype=dt), K, 32, 32,
                           lambda uv, idx: gaussian_surfel(uv))
    ys, xs = torch.meshgrid(torch.arange(32, dtype=dt) + 0.5, torch.arange(32, dtype=dt) + 0.5, indexing="ij")
    sigma_px = f * s / z
    r2 = ((xs - 16) ** 2 + (ys - 16) ** 2) / sigma_px**2
    want = 0.8 * torch.exp(-0.5 * r2) * (r2 <= 9.0)
    want = want * (want >= 1 / 255)
    torch.testing.assert_close(out.alphas[..., 0], want, atol=1e-9, rtol=1e-9)


def test_pretrain_planar_smoke(tmp_path):
    from splatk.stages.pretrain_planar import PlanarPretrainConfig, run_pretrain_planar

    p = run_pretrain_planar(tmp_path / "planar.pt", PlanarPretrainConfig(steps=20, eval_primitives=64))
    meta = json.loads(p.with_suffix(".json").read_text())
    assert meta["target"] == "gaussian_surfel" and math.isfinite(meta["error"]["mae"])
    obj = torch.load(p, weights_only=True)
    LearnedPlanarKernel().load_state_dict(obj["state_dict"])


def test_cli_pretrain_planar(tmp_path):
    from click.testing import CliRunner
    from splatk_cli.main import cli

    out = tmp_path / "p.pt"
    res = CliRunner().invoke(cli, ["pretrain", "--kind", "planar", "--out", str(out), "--steps", "5", "-q"])
    assert res.exit_code == 0, res.output
    assert json.loads(out.with_suffix(".json").read_text())["config"]["steps"] == 5


def test_table_matches_the_row_major_decoder_with_gradients():
    # table() is the feature-major form of sigmoid(logits(nodes, z_after)): same values, same
    # gradients into z_after and every decoder weight (random upstream gradient), and no rows
    k, za = _kernel_and_latents(m=5)
    za.requires_grad_(True)
    ref = torch.sigmoid(k.logits(k.nodes()[None], za[:, None, :])).reshape(-1, k.grid, k.grid)
    new = k.table(za)
    torch.testing.assert_close(new, ref, atol=1e-6, rtol=1e-5)
    up = torch.randn(ref.shape, generator=torch.Generator().manual_seed(3))
    inputs = [za, *k.dec.parameters()]
    for g_new, g_ref in zip(torch.autograd.grad(new, inputs, up), torch.autograd.grad(ref, inputs, up)):
        torch.testing.assert_close(g_new, g_ref, atol=1e-5, rtol=1e-4)
    assert k.table(za[:0]).shape == (0, k.grid, k.grid)
