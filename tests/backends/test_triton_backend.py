"""The Triton ``cuda`` backend agrees with the ``torch`` reference: images and every gradient.

Without a GPU its kernels run in Triton's interpreter (``TRITON_INTERPRET=1``) on CPU tensors.
Triton decides between compiling and interpreting a function when it is defined, and defines
its own library functions on import, so the variable is set while this module imports Triton
and again while its tests run (a fixture), but no longer: no other test sees the interpreter.
The interpreter is slow (a few seconds per render and backward of a dozen tiles), so the scenes
are the small ones of the cpu backend's parity test. The planar rasteriser and the image splats
have Triton kernels too and are checked the same way; ``splatk selftest`` is run through the
CLI for the cuda and cpu backends. With a GPU the same tests run on CUDA tensors.
"""
from __future__ import annotations

import copy
import json
import os
import sys
from pathlib import Path

import pytest
import torch

ON_GPU = torch.cuda.is_available()
if not ON_GPU:
    if "triton" in sys.modules and not os.environ.get("TRITON_INTERPRET"):
        pytest.skip("Triton was imported before this module, without its interpreter", allow_module_level=True)
    with pytest.MonkeyPatch.context() as _mp:
        _mp.setenv("TRITON_INTERPRET", "1")
        pytest.importorskip("triton")
else:
    pytest.importorskip("triton")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_cpu_backend import PROFILES, make_profile_params, make_scene, render_with_grads  # noqa: E402
from test_image_cpu import _splats  # noqa: E402
from test_planar_cpu import H as H_PLANAR  # noqa: E402
from test_planar_cpu import W as W_PLANAR  # noqa: E402
from test_planar_cpu import random_scene  # noqa: E402

from splatk import backends  # noqa: E402
from splatk.errors import BackendUnavailable  # noqa: E402
from splatk.stages.selftest import TOLERANCES  # noqa: E402

DEVICE = "cuda" if ON_GPU else "cpu"
TOL = TOLERANCES["raster"]

# scene -> profiles: every profile on the cheap scenes, the others with a few (the interpreter
# takes 3-10 s per case on 2 cores). "overlap48" is the first 48 of the overlap scene's 400
# splats: still 4 channels, early termination, the alpha clamp and depth ties.
CASES = ([(s, p) for s in ("single", "sparse", "empty") for p in PROFILES]
         + [("offscreen", "student_t"), ("overlap48", "beta"), ("tile_borders", "table8")])


def _scene(name: str):
    if name == "overlap48":
        means, conics, opac, colors, depths, w, h = make_scene("overlap")
        return means[:48], conics[:48], opac[:48], colors[:48], depths[:48], w, h
    return make_scene(name)


@pytest.fixture(scope="module", autouse=True)
def interpreter():
    """TRITON_INTERPRET=1 while this module runs (no GPU: the kernels run on the CPU)."""
    if ON_GPU:
        yield
        return
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TRITON_INTERPRET", "1")
        yield


def _on(scene, device):
    return tuple(t.to(device) if isinstance(t, torch.Tensor) else t for t in scene)


@pytest.mark.parametrize("scene_name,profile_id", CASES)
def test_cuda_matches_torch_reference(scene_name, profile_id):
    kind, k = PROFILES[profile_id]
    scene = _scene(scene_name)
    n, channels, w, h = scene[0].shape[0], scene[3].shape[1], scene[5], scene[6]
    params = make_profile_params(kind, k, n)
    g = torch.Generator().manual_seed(2)
    background = torch.rand(channels, generator=g)
    v_colors = torch.randn(h, w, channels, generator=g)
    v_alphas = torch.randn(h, w, 1, generator=g)

    ref = render_with_grads("torch", scene, kind, params, background, v_colors, v_alphas)
    got = render_with_grads("cuda", _on(scene, DEVICE), kind, None if params is None else params.to(DEVICE),
                            background.to(DEVICE), v_colors.to(DEVICE), v_alphas.to(DEVICE))

    assert got[0].shape == (h, w, channels) and got[1].shape == (h, w, 1)
    torch.testing.assert_close(got[0].cpu(), ref[0], rtol=0, atol=TOL["image"])
    torch.testing.assert_close(got[1].cpu(), ref[1], rtol=0, atol=TOL["image"])
    assert set(got[2]) == set(ref[2])
    for name, ref_grad in ref[2].items():
        got_grad = got[2][name].cpu()
        assert got_grad.shape == ref_grad.shape, name
        scale = float(ref_grad.abs().max()) if ref_grad.numel() else 0.0
        torch.testing.assert_close(got_grad, ref_grad, rtol=0, atol=TOL["grad"] * max(scale, 1e-6),
                                   msg=lambda m, name=name: f"gradient of {name}: {m}")


@pytest.mark.parametrize("term", ["normal", "distortion"])
def test_cuda_planar_geometry_terms_match_torch_reference(term):
    """2DGS's geometry terms (train.planar_regularisers) composite 12 extra channels through the
    planar kernels: the terms and their gradients against the torch reference, on disks that
    cover every pixel well above the normal term's coverage floor."""
    from splatk.functional.surfel_depth import pixel_rays, surfel_geometry_channels
    from splatk.train.planar_regularisers import depth_distortion, normal_consistency

    fn = normal_consistency if term == "normal" else depth_distortion
    g = torch.Generator().manual_seed(5)
    n, w, h = 10, 24, 20
    means = torch.stack([(torch.rand(n, generator=g) - 0.5) * 0.6, (torch.rand(n, generator=g) - 0.5) * 0.6,
                         2.0 + 1.5 * torch.rand(n, generator=g)], 1)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    half = 0.3 * torch.rand(n, generator=g)
    scene = {"means": means, "quats": torch.cat([torch.cos(half)[:, None], torch.sin(half)[:, None] * axis], 1),
             "scales": 0.35 + 0.2 * torch.rand(n, 2, generator=g), "opacities": 0.4 + 0.5 * torch.rand(n, generator=g)}
    K = torch.tensor([[3.0 * w, 0, w / 2], [0, 3.0 * w, h / 2], [0, 0, 1]], device=DEVICE)
    viewmat = torch.eye(4, device=DEVICE)
    results = {}
    for backend in ("torch", "cuda"):
        leaves = {k: v.to(DEVICE).clone().requires_grad_(True) for k, v in scene.items()}
        channels = surfel_geometry_channels(leaves["means"], leaves["quats"], viewmat)
        out = backends.get(backend, DEVICE).rasterize_planar(
            leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], channels, viewmat, K, w, h,
            backends.PlanarProfile("gaussian_surfel"), torch.zeros(12, device=DEVICE))
        assert float(out.alphas.detach().min()) > 0.05
        value = fn(out.colors, out.alphas, pixel_rays(K, w, h))
        value.backward()
        results[backend] = float(value.detach()), {k: v.grad.cpu() for k, v in leaves.items()}
    ref, got = results["torch"], results["cuda"]
    assert ref[0] > 1e-6
    assert got[0] == pytest.approx(ref[0], rel=2e-5)
    for name, ref_grad in ref[1].items():
        scale = max(float(ref_grad.abs().max()), 1e-6)
        # float32: under the interpreter the gradients differ by up to 1e-5 of the largest one
        torch.testing.assert_close(got[1][name], ref_grad, rtol=0, atol=2e-4 * scale,
                                   msg=lambda m, name=name: f"gradient of {name}: {m}")


def test_binning_lists_each_tiles_primitives_front_to_back():
    """bin_pairs against a brute-force binning: per tile, the primitives whose support box
    meets it, by depth with ties by index (the overlap scene has many equal depths)."""
    from splatk.backends.torch_ref import support_bboxes
    from splatk.backends.triton_binning import bin_pairs

    means, conics, _, _, depths, w, h = make_scene("overlap")
    flat_ids, offsets, tiles_x = bin_pairs(means, conics, depths, w, h)
    x0, x1, y0, y1 = support_bboxes(means, conics, w, h)
    tiles_y = (h + 15) // 16
    assert offsets.numel() == tiles_x * tiles_y + 1 and int(offsets[-1]) == flat_ids.numel()
    for t in range(tiles_x * tiles_y):
        tx, ty = t % tiles_x, t // tiles_x
        meets = ((x0 < 16 * tx + 16) & (x1 > 16 * tx) & (y0 < 16 * ty + 16) & (y1 > 16 * ty)
                 & (x1 > x0) & (y1 > y0))
        expected = sorted(torch.nonzero(meets).flatten().tolist(), key=lambda i: (float(depths[i]), i))
        assert flat_ids[int(offsets[t]):int(offsets[t + 1])].tolist() == expected, t


def _weighted_sum(*outs):
    """A fixed random weighting of the outputs (drawn on the CPU: the same on every device)."""
    gen = torch.Generator().manual_seed(7)
    return sum((o * torch.randn(o.shape, generator=gen).to(o.device)).sum() for o in outs)


def _planar_render(scene, table, kind, backend, bg):
    # clones: on the CPU .to(DEVICE) is the same tensor, whose .grad the next render's backward
    # would accumulate into in place, so both renders' gradients would be one tensor
    leaves = {k: v.to(DEVICE).clone().requires_grad_(k not in ("viewmat", "K")) for k, v in scene.items()}
    tab = None if table is None else table.to(DEVICE).clone().requires_grad_(True)
    bgl = bg.to(DEVICE).clone().requires_grad_(True)
    out = backends.get(backend, DEVICE).rasterize_planar(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"], leaves["viewmat"],
        leaves["K"], W_PLANAR, H_PLANAR, backends.PlanarProfile(kind, tab), bgl)
    _weighted_sum(out.colors, out.alphas).backward()
    grads = {k: leaves[k].grad.cpu() for k in ("means", "quats", "scales", "opacities", "colors")}
    grads["background"] = bgl.grad.cpu()
    if tab is not None:
        grads["table"] = tab.grad.cpu()
    return out.colors.detach().cpu(), out.alphas.detach().cpu(), grads


@pytest.mark.parametrize("kind,grid", [("gaussian_surfel", 0), ("grid", 6)])
def test_cuda_planar_matches_torch_reference(kind, grid):
    """The planar rasteriser's Triton kernels: image and the gradients of every input, through
    the homographies to means, quats and scales (the native planar test's scene)."""
    scene, table = random_scene(20, seed=0, dtype=torch.float32, grid=grid)
    bg = torch.rand(3, generator=torch.Generator().manual_seed(3))
    ref = _planar_render(scene, table, kind, "torch", bg)
    got = _planar_render(scene, table, kind, "cuda", bg)
    tol = TOLERANCES["planar"]
    torch.testing.assert_close(got[0], ref[0], rtol=0, atol=tol["image"])
    torch.testing.assert_close(got[1], ref[1], rtol=0, atol=tol["image"])
    assert set(got[2]) == set(ref[2])
    for name, ref_grad in ref[2].items():
        scale = max(float(ref_grad.abs().max()), 1e-6)
        torch.testing.assert_close(got[2][name], ref_grad, rtol=0, atol=tol["grad"] * scale,
                                   msg=lambda m, name=name: f"gradient of {name}: {m}")


@pytest.mark.parametrize("kernel", ["gaussian", "gabor", "learned"])
def test_cuda_image_splats_match_the_torch_path(kernel):
    """The image splats' Triton op against the model's torch path (the native image test's
    splats, smaller): image and every parameter's gradient."""
    splats, results = _splats(kernel, torch.float32, n=30, h=24, w=32), []
    for backend in ("torch", "cuda"):
        model = copy.deepcopy(splats).to(DEVICE)
        model.backend = backend
        img = model.render()
        _weighted_sum(img).backward()
        results.append((img.detach().cpu(), {n: p.grad.cpu() for n, p in model.named_parameters()}))
    assert model.uses_native()
    (img_ref, grads_ref), (img, grads) = results
    tol = TOLERANCES["image"]
    torch.testing.assert_close(img, img_ref, rtol=0, atol=tol["image"])
    for name, ref in grads_ref.items():
        scale = float(ref.abs().max())
        assert scale > 0, f"{name}: the test passes no gradient"
        torch.testing.assert_close(grads[name], ref, rtol=0, atol=tol["grad"] * scale, msg=name)


def test_triton_kernels_run_not_the_torch_fallback(monkeypatch):
    """The parity above is the Triton kernels' (a float32 render must not reach the torch path)."""
    from splatk.backends.torch_backend import TorchBackend

    def refuse(*args, **kwargs):
        raise AssertionError("the cuda backend fell back to the torch rasteriser")

    monkeypatch.setattr(TorchBackend, "rasterize", refuse)
    monkeypatch.setattr(TorchBackend, "rasterize_planar", refuse)
    be = backends.get("cuda", DEVICE)
    means, conics, opac, colors, depths, w, h = _on(make_scene("single"), DEVICE)
    out = be.rasterize(means, conics, opac, colors, depths, backends.Profile("gaussian"), w, h,
                       torch.zeros(3, device=DEVICE))
    assert float(out.alphas.max()) > 0.5
    disk = [torch.tensor(v, device=DEVICE) for v in ([[0.0, 0.0, 3.0]], [[1.0, 0.0, 0.0, 0.0]], [[0.3, 0.2]],
                                                     [0.9], [[1.0, 0.5, 0.2]])]
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]], device=DEVICE)
    out = be.rasterize_planar(*disk, torch.eye(4, device=DEVICE), K, 16, 16, backends.PlanarProfile("gaussian_surfel"))
    assert float(out.alphas.max()) > 0.5


def test_other_dtypes_and_wide_colours_use_the_torch_rasteriser():
    means, conics, opac, colors, depths, w, h = make_scene("single")
    be = backends.get("cuda", DEVICE)
    ref = backends.get("torch", "cpu")
    wide = torch.rand(1, 70)  # above MAX_CHANNELS
    for args in [(means.double(), conics.double(), opac.double(), colors.double()),
                 (means, conics, opac, wide)]:
        bg = torch.zeros(args[3].shape[1], dtype=args[3].dtype)
        got = be.rasterize(*(a.to(DEVICE) for a in args), depths.to(DEVICE), backends.Profile("gaussian"), w, h,
                           bg.to(DEVICE))
        want = ref.rasterize(*args, depths, backends.Profile("gaussian"), w, h, bg)
        assert got.colors.dtype == args[3].dtype
        torch.testing.assert_close(got.colors.cpu(), want.colors)


@pytest.mark.skipif(ON_GPU, reason="checks the CPU machine's availability rules")
def test_cpu_availability_follows_the_interpreter_and_auto_never_picks_it(monkeypatch):
    assert backends.is_available("cuda", "cpu")  # the interpreter is on (fixture)
    if backends.is_available("cpu", "cpu"):
        assert backends.resolve_backend("auto", "cpu") == "cpu"
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    assert not backends.is_available("cuda", "cpu")
    with pytest.raises(BackendUnavailable, match="CUDA tensors only.*--backend cpu"):
        backends.get("cuda", "cpu")


def _selftest(args):
    from click.testing import CliRunner

    from splatk_cli.main import cli

    return CliRunner().invoke(cli, ["selftest", *args])


@pytest.mark.parametrize("name", ["cuda", "cpu"])
def test_selftest_json_passes(name):
    if name == "cpu" and not backends.is_available("cpu", "cpu"):
        pytest.skip("native cpu backend could not be built here")
    res = _selftest(["--backend", name, "--json"])
    assert res.exit_code == 0, res.output
    report = json.loads(res.output)["backends"][name]
    assert report["passed"] is True
    cases = report["cases"]
    assert {"raster_gaussian", "raster_beta", "raster_student_t", "raster_table4", "planar_grid",
            "image_gaussian"} <= set(cases)
    assert all(c["passed"] and c["image_error"] <= c["image_tolerance"] for c in cases.values())
    assert report["max_image_error"] == max(c["image_error"] for c in cases.values())
    # the Triton rasteriser is the cuda backend's own op and really differs from the reference
    assert cases["raster_beta"]["own_op"] and 0 < cases["raster_beta"]["grad_error"] <= TOL["grad"]
    assert {"image_gabor", "image_learned"} <= set(cases)
    assert cases["planar_grid"]["own_op"] and cases["image_learned"]["own_op"]


def test_selftest_fails_a_wrong_backend(monkeypatch):
    """A backend whose image is off fails its cases and the command exits 1."""
    from splatk.backends.registry import BACKENDS
    from splatk.backends.torch_backend import TorchBackend

    class Darker(TorchBackend):
        name = "darker"

        def rasterize(self, *args):
            out = super().rasterize(*args)
            return out._replace(colors=out.colors * 0.99)

    class NanPlanar(TorchBackend):
        name = "nan_planar"

        def rasterize_planar(self, *args):
            out = super().rasterize_planar(*args)
            return out._replace(colors=out.colors * float("nan"))

    monkeypatch.setitem(BACKENDS, "darker", Darker)
    monkeypatch.setitem(BACKENDS, "nan_planar", NanPlanar)
    res = _selftest(["--backend", "darker"])
    assert res.exit_code == 1, res.output
    assert "darker (cuda): FAIL" in res.output if ON_GPU else "darker (cpu): FAIL" in res.output
    assert "raster_gaussian" in res.output and "planar_grid" in res.output
    # NaN images fail too, and the JSON stays JSON (the infinite error is null)
    res = _selftest(["--backend", "nan_planar", "--json"])
    assert res.exit_code == 1, res.output
    cases = json.loads(res.output)["backends"]["nan_planar"]["cases"]
    assert cases["planar_grid"]["passed"] is False and cases["planar_grid"]["image_error"] is None
    assert cases["raster_gaussian"]["passed"] is True


def test_selftest_named_unavailable_backend_is_one_line_error(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    if ON_GPU:
        pytest.skip("cuda runs here")
    res = _selftest(["--backend", "cuda"])
    assert res.exit_code == 2
    assert res.output.strip().startswith("splatk: error:") and len(res.output.strip().splitlines()) == 1
