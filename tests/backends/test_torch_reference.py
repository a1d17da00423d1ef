"""The ``torch`` reference agrees with a naive dense renderer, for every profile kind.

The naive renderer is written from the contract in ``splatk.backends`` alone: loop over the
primitives in stable depth order, evaluate every pixel, composite front to back with the
1/255 skip and the T < 1e-4 stop. It shares no code with ``torch_ref``.
"""
from __future__ import annotations

import math

import pytest
import torch

from splatk.backends import Profile, rasterize


def naive_render(means, conics, opac, colors, depths, kind, params, width, height, background):
    """Dense float64 renderer: [H, W, C] colours and [H, W, 1] alphas."""
    d = torch.float64
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=d) + 0.5, torch.arange(width, dtype=d) + 0.5, indexing="ij"
    )
    T = torch.ones(height, width, dtype=d)
    done = torch.zeros(height, width, dtype=torch.bool)
    img = torch.zeros(height, width, colors.shape[1], dtype=d)
    order = sorted(range(means.shape[0]), key=lambda i: (float(depths[i]), i))
    for i in order:
        dx, dy = xs - float(means[i, 0]), ys - float(means[i, 1])
        a, b, c = (float(v) for v in conics[i])
        r2 = a * dx * dx + 2 * b * dx * dy + c * dy * dy
        inside = (r2 < 1) & (r2 >= 0)
        r2c = torch.where(inside, r2, torch.zeros_like(r2))
        if kind == "gaussian":
            prof = torch.exp(-4.5 * r2c)
        elif kind == "beta":
            prof = (1 - r2c) ** float(params[i, 0])
        elif kind == "student_t":
            nu = float(params[i, 0])
            prof = (1 + 9 * r2c / nu) ** (-(nu + 2) / 2)
        else:  # piecewise linear through (j / (k - 1), d_j)
            k = params.shape[1]
            t = torch.sqrt(r2c) * (k - 1)
            j = torch.clamp(torch.floor(t), 0, k - 2).long()
            lam = t - j
            samples = params[i].to(d)
            prof = (1 - lam) * samples[j] + lam * samples[j + 1]
        alpha = torch.clamp(float(opac[i]) * prof, max=0.999)
        live = inside & (alpha >= 1 / 255) & ~done
        t_next = T * (1 - alpha)
        stop = live & (t_next < 1e-4)
        blend = live & ~stop
        img += torch.where(blend, alpha * T, torch.zeros_like(T))[..., None] * colors[i].to(d)
        T = torch.where(blend, t_next, T)
        done |= stop
    img += T[..., None] * background.to(d)
    return img, (1 - T)[..., None]


def _scene(seed: int, n: int, width: int, height: int, sig_lo: float, sig_hi: float, opac_lo: float):
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    means = torch.rand(n, 2, generator=g, dtype=d) * torch.tensor([width + 8, height + 8], dtype=d) - 4
    sig = torch.rand(n, 2, generator=g, dtype=d) * (sig_hi - sig_lo) + sig_lo
    th = torch.rand(n, generator=g, dtype=d) * math.pi
    c, s = torch.cos(th), torch.sin(th)
    i0, i1 = 1 / sig[:, 0] ** 2, 1 / sig[:, 1] ** 2
    conics = torch.stack([c * c * i0 + s * s * i1, c * s * (i0 - i1), s * s * i0 + c * c * i1], -1) / 9
    opac = torch.rand(n, generator=g, dtype=d) * (1 - opac_lo) + opac_lo
    opac[::5] = 1.0  # alpha clamp
    colors = torch.rand(n, 3, generator=g, dtype=d)
    depths = torch.round(torch.rand(n, generator=g, dtype=d) * 8) / 2  # ties
    background = torch.rand(3, generator=g, dtype=d)
    return means, conics, opac, colors, depths, background


@pytest.mark.parametrize(
    "kind,k", [("gaussian", None), ("beta", None), ("student_t", None), ("table", 2), ("table", 5)]
)
@pytest.mark.parametrize(
    "scene", [(0, 40, 35, 21, 0.5, 5.0, 0.0), (1, 150, 24, 20, 3.0, 8.0, 0.6)],
    ids=["sparse", "overlapping"],
)
def test_reference_matches_naive_renderer(kind, k, scene):
    seed, n, width, height = scene[:4]
    means, conics, opac, colors, depths, bg = _scene(*scene)
    g = torch.Generator().manual_seed(seed + 10)
    if kind == "gaussian":
        params = None
    elif kind in ("beta", "student_t"):
        params = torch.rand(n, 1, generator=g, dtype=torch.float64) * 4 + 0.5
    else:
        params = torch.rand(n, k, generator=g, dtype=torch.float64) * 1.3
    out = rasterize(means, conics, opac, colors, depths, Profile(kind, params), width, height, bg,
                    backend="torch")
    img, alphas = naive_render(means, conics, opac, colors, depths, kind, params, width, height, bg)
    torch.testing.assert_close(out.colors, img, rtol=0, atol=1e-10)
    torch.testing.assert_close(out.alphas, alphas, rtol=0, atol=1e-10)
    if scene[0] == 1:  # the overlapping scene must exercise the early stop
        assert float(alphas.max()) > 1 - 1e-3
