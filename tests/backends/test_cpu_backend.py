"""The native ``cpu`` backend agrees with the ``torch`` reference: images and every gradient.

One parametrised body runs every (scene, profile) pair through both backends with the same
random upstream gradients; float64 ``gradcheck`` checks the native backward on tiny inputs.
The first test in a fresh cache compiles the extension (about 15-25 s on 2 cores).
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from splatk.backends import Profile, is_available, rasterize, resolve_backend

# Building happens here, at collection, the first time (the fallback tests below run anyway).
needs_cpu = pytest.mark.skipif(
    not is_available("cpu"), reason="native cpu backend could not be built here"
)

PROFILES = {  # id -> (kind, k)
    "gaussian": ("gaussian", None),
    "beta": ("beta", None),
    "student_t": ("student_t", None),
    "table2": ("table", 2),
    "table4": ("table", 4),
    "table8": ("table", 8),
    "table20": ("table", 20),  # k > 16: the native backend's general (gather) table path
}

# Tolerances for float32 cpu vs float32 torch, by output; gradients are compared with
# atol = TOL * max|reference gradient| (and rtol = TOL). The native r2 rounds exactly like the
# reference's (no FMA), so the differences left come from the exp/log polynomials (about 1 ulp
# vs Sleef), float64 vs log-space transmittance and summation order. Worst measured over
# SCENES x PROFILES in brackets; the table keeps about 10x headroom.
TOL = {
    "colors": 1e-5,  # [8e-7 overlap-table20]
    "alphas": 1e-5,  # [1.4e-6 tile_borders-table20]
    "means2d": 2e-5,  # [1.5e-6 overlap-gaussian]
    "conics": 2e-5,  # [1.0e-6 random-table20]
    "opacities": 2e-5,  # [7.5e-7 random-table20]
    "colors_grad": 2e-5,  # [6.8e-7 overlap-table8]
    "params": 2e-5,  # [2.0e-6 sparse-student_t]
    "background": 2e-5,  # [1.1e-6 overlap-table8]
}


def _conics(sigmas: torch.Tensor, thetas: torch.Tensor) -> torch.Tensor:
    """Normalised conics (support at 3 sigma) of rotated ellipses: inv(R diag(s^2) R^T) / 9."""
    c, s = torch.cos(thetas), torch.sin(thetas)
    i0, i1 = 1.0 / sigmas[:, 0] ** 2, 1.0 / sigmas[:, 1] ** 2
    return torch.stack([c * c * i0 + s * s * i1, c * s * (i0 - i1), s * s * i0 + c * c * i1], -1) / 9.0


def make_scene(name: str, seed: int = 0):
    """(means2d, conics, opacities, colors, depths, width, height) for a named test scene."""
    g = torch.Generator().manual_seed(seed)

    def u(shape, lo, hi):
        return torch.rand(shape, generator=g) * (hi - lo) + lo

    channels = 3
    if name == "random":  # width and height not multiples of 16
        w, h, n = 37, 29, 60
        means = torch.stack([u(n, -4, w + 4), u(n, -4, h + 4)], -1)
        sig = u((n, 2), 0.5, 6.0)
        opac = u(n, 0.0, 1.0)
        depths = u(n, 1.0, 5.0)
    elif name == "overlap":  # heavy overlap: early termination, alpha clamp, depth ties
        w, h, n, channels = 40, 24, 400, 4
        means = torch.stack([u(n, 0, w), u(n, 0, h)], -1)
        sig = u((n, 2), 3.0, 9.0)
        opac = u(n, 0.5, 1.0)
        opac[::7] = 1.0
        depths = torch.round(u(n, 1.0, 5.0) * 4) / 4  # many equal depths: ties by index
    elif name == "tile_borders":  # centres on and next to tile borders, elongated splats
        w, h, n = 48, 48, 36
        grid = torch.tensor([15.5, 16.0, 16.5, 31.9, 32.0, 32.1])
        means = torch.stack([grid.repeat(6), grid.repeat_interleave(6)], -1)
        sig = torch.stack([u(n, 0.5, 2.0), u(n, 3.0, 12.0)], -1)
        opac = u(n, 0.2, 1.0)
        depths = u(n, 1.0, 5.0)
    elif name == "offscreen":  # partly and fully outside the image
        w, h, n = 33, 17, 50
        means = torch.stack([u(n, -15, w + 15), u(n, -15, h + 15)], -1)
        sig = u((n, 2), 1.0, 8.0)
        opac = u(n, 0.1, 1.0)
        depths = u(n, 1.0, 5.0)
    elif name == "sparse":  # most tiles empty
        w, h, n = 80, 64, 3
        means = torch.tensor([[5.0, 5.0], [50.3, 40.7], [79.0, 20.0]])
        sig = u((n, 2), 0.7, 3.0)
        opac = u(n, 0.3, 1.0)
        depths = u(n, 1.0, 5.0)
    elif name == "single":
        w, h, n = 16, 16, 1
        means = torch.tensor([[7.3, 8.9]])
        sig = torch.tensor([[2.0, 4.0]])
        opac = torch.tensor([0.8])
        depths = torch.tensor([2.0])
    elif name == "empty":
        w, h, n = 20, 12, 0
        means = torch.zeros(0, 2)
        sig = torch.ones(0, 2)
        opac = torch.zeros(0)
        depths = torch.zeros(0)
    else:
        raise KeyError(name)
    conics = _conics(sig, u(n, 0.0, math.pi))
    colors = u((n, channels), 0.0, 1.0)
    return means, conics, opac, colors, depths, w, h


SCENES = ["random", "overlap", "tile_borders", "offscreen", "sparse", "single", "empty"]


def make_profile_params(kind: str, k: int | None, n: int, seed: int = 1) -> torch.Tensor | None:
    g = torch.Generator().manual_seed(seed)
    if kind == "gaussian":
        return None
    if kind == "beta":
        return torch.rand(n, 1, generator=g) * 3.7 + 0.3
    if kind == "student_t":
        return torch.rand(n, 1, generator=g) * 9.5 + 0.5
    return torch.rand(n, k, generator=g) * 1.2  # samples > 1 exercise the 0.999 clamp


def render_with_grads(backend, scene, kind, params, background, v_colors, v_alphas):
    means, conics, opac, colors, depths, w, h = scene
    leaves = [t.clone().requires_grad_(True) for t in (means, conics, opac, colors, background)]
    p = None if params is None else params.clone().requires_grad_(True)
    out = rasterize(
        leaves[0], leaves[1], leaves[2], leaves[3], depths, Profile(kind, p), w, h, leaves[4],
        backend=backend,
    )
    ((out.colors * v_colors).sum() + (out.alphas * v_alphas).sum()).backward()
    names = ["means2d", "conics", "opacities", "colors_grad", "background"]
    if p is not None:
        leaves.append(p)
        names.append("params")
    # a leaf the render does not reach (N = 0 in the reference) has gradient None: zeros
    grads = {
        name: torch.zeros_like(leaf) if leaf.grad is None else leaf.grad
        for name, leaf in zip(names, leaves)
    }
    return out.colors.detach(), out.alphas.detach(), grads


@needs_cpu
@pytest.mark.parametrize("profile_id", list(PROFILES))
@pytest.mark.parametrize("scene_name", SCENES)
def test_cpu_matches_torch_reference(scene_name, profile_id):
    kind, k = PROFILES[profile_id]
    scene = make_scene(scene_name)
    n, channels, w, h = scene[0].shape[0], scene[3].shape[1], scene[5], scene[6]
    params = make_profile_params(kind, k, n)
    g = torch.Generator().manual_seed(2)
    background = torch.rand(channels, generator=g)
    v_colors = torch.randn(h, w, channels, generator=g)
    v_alphas = torch.randn(h, w, 1, generator=g)

    ref = render_with_grads("torch", scene, kind, params, background, v_colors, v_alphas)
    got = render_with_grads("cpu", scene, kind, params, background, v_colors, v_alphas)

    assert got[0].shape == (h, w, channels) and got[1].shape == (h, w, 1)
    torch.testing.assert_close(got[0], ref[0], rtol=0, atol=TOL["colors"])
    torch.testing.assert_close(got[1], ref[1], rtol=0, atol=TOL["alphas"])
    assert set(got[2]) == set(ref[2])
    for name, ref_grad in ref[2].items():
        got_grad = got[2][name]
        assert got_grad.shape == ref_grad.shape, name
        scale = float(ref_grad.abs().max()) if ref_grad.numel() else 0.0
        torch.testing.assert_close(
            got_grad, ref_grad, rtol=TOL[name], atol=TOL[name] * max(scale, 1e-6),
            msg=lambda m, name=name: f"gradient of {name}: {m}",
        )


@needs_cpu
def test_cpu_deterministic_across_threads():
    """Backward has no atomics: bitwise-identical gradients for 1 and 2 threads."""
    scene = make_scene("overlap")
    kind, k = PROFILES["table4"]
    params = make_profile_params(kind, k, scene[0].shape[0])
    g = torch.Generator().manual_seed(5)
    bg = torch.rand(scene[3].shape[1], generator=g)
    v_c = torch.randn(scene[6], scene[5], scene[3].shape[1], generator=g)
    v_a = torch.randn(scene[6], scene[5], 1, generator=g)
    before = torch.get_num_threads()
    try:
        runs = []
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            runs.append(render_with_grads("cpu", scene, kind, params, bg, v_c, v_a))
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        assert torch.equal(other[0], runs[0][0])
        for name in runs[0][2]:
            assert torch.equal(other[2][name], runs[0][2][name]), name


def _gradcheck_inputs(kind: str, k: int | None, seed: int):
    # Opacities <= 0.8 and at most 4 splats keep T above 1e-4 and alpha below the clamp, so the
    # render is smooth in every input away from the (measure-zero) support and 1/255 edges.
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    n, w, h, channels = 4, 20, 9, 3  # two tiles wide, partial tiles
    means = torch.rand(n, 2, generator=g, dtype=d) * torch.tensor([w, h], dtype=d)
    sig = torch.rand(n, 2, generator=g, dtype=d) * 2.5 + 1.5
    conics = _conics(sig, torch.rand(n, generator=g, dtype=d) * math.pi)
    opac = torch.rand(n, generator=g, dtype=d) * 0.6 + 0.2
    colors = torch.rand(n, channels, generator=g, dtype=d)
    depths = torch.rand(n, generator=g, dtype=d)
    bg = torch.rand(channels, generator=g, dtype=d)
    if kind == "gaussian":
        params = None
    elif kind == "beta":
        params = torch.rand(n, 1, generator=g, dtype=d) * 2.5 + 0.5
    elif kind == "student_t":
        params = torch.rand(n, 1, generator=g, dtype=d) * 7 + 1
    else:
        params = torch.rand(n, k, generator=g, dtype=d) * 0.9 + 0.1
    return means, conics, opac, colors, bg, params, depths, w, h


@pytest.mark.gradcheck
@pytest.mark.parametrize("backend", [pytest.param("cpu", marks=needs_cpu), "torch"])
@pytest.mark.parametrize("profile_id", ["gaussian", "beta", "student_t", "table2", "table8", "table20"])
def test_gradcheck_float64(backend, profile_id):
    kind, k = PROFILES[profile_id]
    means, conics, opac, colors, bg, params, depths, w, h = _gradcheck_inputs(kind, k, seed=3)
    inputs = [means, conics, opac, colors, bg] + ([params] if params is not None else [])
    inputs = [t.clone().requires_grad_(True) for t in inputs]

    def fn(*xs):
        p = Profile(kind, xs[5] if params is not None else None)
        out = rasterize(xs[0], xs[1], xs[2], xs[3], depths, p, w, h, xs[4], backend=backend)
        return out.colors, out.alphas

    # The native backward is cheap: check the full Jacobian. The reference's backward is slow;
    # gradcheck's fast mode checks it along random projections.
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, fast_mode=backend == "torch")


@needs_cpu
def test_auto_prefers_cpu_and_float64_runs_natively():
    assert resolve_backend("auto", "cpu") == "cpu"
    means, conics, opac, colors, bg, params, depths, w, h = _gradcheck_inputs("table", 4, 0)
    out = rasterize(means, conics, opac, colors, depths, Profile("table", params), w, h, bg)
    assert out.colors.dtype == torch.float64


def test_build_failure_warns_once_and_auto_falls_back(tmp_path):
    """No usable compiler: available() is False, one RuntimeWarning, auto resolves to torch."""
    code = textwrap.dedent(
        """
        import warnings
        warnings.simplefilter("always")
        with warnings.catch_warnings(record=True) as caught:
            from splatk.backends import resolve_backend, is_available
            from splatk.backends import cpu_native
            assert not cpu_native.available()
            assert not is_available("cpu")
            assert resolve_backend("auto", "cpu") == "torch"
        msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
        assert len(msgs) == 1 and "could not be built" in msgs[0], msgs
        print("OK", cpu_native.unavailable_reason())
        """
    )
    env = dict(os.environ, CXX=str(tmp_path / "no-such-compiler"), SPLATK_CACHE_DIR=str(tmp_path))
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and "OK" in res.stdout, res.stdout + res.stderr


def test_build_key_tracks_flags(monkeypatch):
    from splatk.backends import cpu_native

    monkeypatch.setenv("SPLATK_NATIVE_MARCH", "1")
    native = cpu_native._build_key(cpu_native._flags())
    monkeypatch.setenv("SPLATK_NATIVE_MARCH", "0")
    portable = cpu_native._build_key(cpu_native._flags())
    assert native != portable and "-march=native" not in cpu_native._flags()
