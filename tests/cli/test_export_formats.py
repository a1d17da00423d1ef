"""`splatk export --format splat|spz` and the Gaussian approximation report, through the CLI on
short fits of the demo scene. Every file is opened with a reader that shares no code with
splatk's writers: ``.splat`` with a numpy structured dtype written here from antimatter15's
published layout, SPZ with gsply (a third-party SPZ reader), the PLY with plyfile; the decoded
values are checked against the model they came from, within each format's quantisation step."""
from __future__ import annotations

import gzip
import json
import math
import struct

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from plyfile import PlyData

from splatk import backends
from splatk.colors import make_color_model
from splatk.data import load_scene
from splatk.export_formats import Gaussians
from splatk.export_formats.spz import check_spz_range, write_spz
from splatk.functional.projection import quats_to_rotmats
from splatk.functional.sh import sh_basis
from splatk.kernels import make_kernel
from splatk.metrics import psnr
from splatk.models.io import load_model
from splatk.models.volumetric import SplatModel
from splatk_cli.main import cli

SH_DEGREE = 3
SH_C0 = 0.28209479177387814  # Y_0^0, as every 3DGS viewer decodes f_dc
#: antimatter15/splat's row: position f32x3, scale f32x3 (linear), RGBA u8x4, quaternion u8x4 (w x y z)
SPLAT_ROW = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("sx", "<f4"), ("sy", "<f4"), ("sz", "<f4"),
                      ("r", "u1"), ("g", "u1"), ("b", "u1"), ("a", "u1"),
                      ("qw", "u1"), ("qx", "u1"), ("qy", "u1"), ("qz", "u1")])
#: SPZ stores right-up-back coordinates, splatk right-down-front: a half turn about x
RUB_FROM_RDF = np.diag([1.0, -1.0, -1.0]).astype(np.float32)


def invoke(*args):
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == 0, f"{res.output}\n{res.exception!r}"
    return res


def fit(root, name, *extra):
    n = torch.get_num_threads()
    invoke("fit", root / "scene", "--out", root / name, "--iters", "60", "--budget", "200", "--init", "random",
           "--sh-degree", SH_DEGREE, "--backend", "torch", "--seed", "2", "--threads", "1", "-q", *extra)
    torch.set_num_threads(n)
    return root / name


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    from splatk.data.synthetic import make_demo_scene

    root = tmp_path_factory.mktemp("export_formats")
    make_demo_scene(root / "scene", num_views=9, size=32)  # 7 train, 2 test views
    return root


@pytest.fixture(scope="module")
def gaussian_run(root):
    return fit(root, "gaussian")


@pytest.fixture(scope="module")
def beta_run(root):
    return fit(root, "beta", "--kernel", "beta")


def prims_of(run):
    model, _ = load_model(run / "model.pt")
    return model, {k: v.detach().numpy() for k, v in model.prims.items()}


def match_rows(decoded: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """The row of ``expected`` that each decoded row is (files may reorder, and a fit can leave
    two primitives at one position): the one-to-one assignment with the least total difference
    of the features ([N, F] each, in comparable units). The callers then check every value."""
    from scipy.optimize import linear_sum_assignment

    assert decoded.shape == expected.shape
    rows, idx = linear_sum_assignment(np.abs(decoded[:, None, :] - expected[None]).sum(-1))
    assert np.array_equal(rows, np.arange(len(decoded)))
    return idx


def test_splat_matches_the_published_layout(gaussian_run, tmp_path):
    out = tmp_path / "model.splat"
    res = invoke("export", gaussian_run, "--format", "splat", "--out", out, "--backend", "torch")
    model, p = prims_of(gaussian_run)
    n = model.num_primitives
    raw = out.read_bytes()
    assert len(raw) == 32 * n  # no header, 32 bytes a splat
    rows = np.frombuffer(raw, SPLAT_ROW)
    pos = np.stack([rows["x"], rows["y"], rows["z"]], 1)
    alpha = 255 / (1 + np.exp(-p["opacity_logits"]))
    scales = np.stack([rows["sx"], rows["sy"], rows["sz"]], 1)
    idx = match_rows(np.concatenate([pos, np.log(scales), rows["a"][:, None] / 255], 1),
                     np.concatenate([p["means"], p["log_scales"], alpha[:, None] / 255], 1))
    np.testing.assert_array_equal(pos, p["means"][idx])  # float32 positions, stored exactly
    np.testing.assert_allclose(scales, np.exp(p["log_scales"][idx]), rtol=1e-6)  # Gaussian kernel: x1, linear
    rgb = np.clip((0.5 + SH_C0 * p["sh0"][idx, 0, :]) * 255, 0, 255)
    assert np.abs(np.stack([rows["r"], rows["g"], rows["b"]], 1) - rgb).max() <= 1
    assert np.abs(rows["a"] - alpha[idx]).max() <= 1
    q = p["quats"][idx] / np.linalg.norm(p["quats"][idx], axis=1, keepdims=True)
    decoded_q = (np.stack([rows["qw"], rows["qx"], rows["qy"], rows["qz"]], 1).astype(np.float32) - 128) / 128
    assert np.abs(decoded_q - q).max() <= 1 / 128 + 1e-6
    # the viewer's order: descending size * opacity, so the big opaque splats stream in first
    importance = np.prod(scales, 1) / (1 + np.exp(-p["opacity_logits"][idx]))
    assert np.all(importance[1:] <= importance[:-1] * (1 + 1e-5))
    # .splat keeps one colour: the SH bands are an approximation the command reports and measures
    assert "SH degree 3 colour reduced to degree 0" in res.stderr and "test PSNR" in res.stderr


def gsply_read_spz(path):
    gsply = pytest.importorskip("gsply")
    gsply.use_backend("auto")  # its C++ reader where the wheel has one (the numba one compiles for ~10 s)
    return gsply.read_spz(str(path))


def spz_header(path):
    magic, version, n, degree, frac_bits, flags, _ = struct.unpack("<4sIIBBBB", gzip.decompress(path.read_bytes())[:16])
    return magic, version, n, degree, frac_bits, flags


def sh_flip_signs(degree: int) -> np.ndarray:
    """Sign each SH coefficient takes under a half turn about x, from the basis itself:
    Y_k(F d) / Y_k(d) at a generic direction (every real SH function is even or odd in y, z)."""
    d = torch.nn.functional.normalize(torch.tensor([[0.3, 0.5, 0.7]]), dim=-1)
    flipped = d @ torch.from_numpy(RUB_FROM_RDF).T
    ratio = sh_basis(flipped, degree) / sh_basis(d, degree)
    signs = ratio[0, 1:].numpy()
    assert np.allclose(np.abs(signs), 1, atol=1e-5)
    return np.sign(signs)


def check_spz_against(data, g: Gaussians, fractional_bits: int = 12):
    """gsply's decoded SPZ (right-up-back) against the Gaussians written (right-down-front)."""
    means = data.means @ RUB_FROM_RDF
    idx = match_rows(np.concatenate([means, data.scales, data.sh0], 1),
                     np.concatenate([g.means, g.log_scales, g.sh0], 1))
    assert np.abs(means - g.means[idx]).max() <= 0.5 / 2**fractional_bits + 1e-6
    np.testing.assert_allclose(data.scales, g.log_scales[idx], atol=1 / 32 + 1e-6)  # log scale, steps of 1/16
    alpha = 1 / (1 + np.exp(-data.opacities))
    assert np.abs(alpha - 1 / (1 + np.exp(-g.opacity_logits[idx]))).max() <= 0.5 / 255 + 1e-3
    np.testing.assert_allclose(data.sh0, g.sh0[idx], atol=0.5 / 255 / 0.15 + 1e-5)
    # rotations: the same rotation seen from the other frame, R' = F R F
    R = quats_to_rotmats(torch.from_numpy(g.quats[idx])).numpy()
    R_read = quats_to_rotmats(torch.from_numpy(np.ascontiguousarray(data.quats, dtype=np.float32))).numpy()
    np.testing.assert_allclose(R_read, RUB_FROM_RDF @ R @ RUB_FROM_RDF, atol=6e-3)
    degree = g.sh_degree
    if degree:
        signs = sh_flip_signs(degree)
        expected = np.clip(g.sh_rest[idx] * signs[None, :, None], -1, 127 / 128)
        err = np.abs(data.shN - expected)
        assert err[:, :3].max() <= 4 / 128 + 1 / 256 + 1e-6  # degree 1: buckets of 8 / 128
        assert err[:, 3:].max() <= 8 / 128 + 1 / 256 + 1e-6  # degrees 2, 3: buckets of 16 / 128


def test_spz_reads_back_with_gsply(gaussian_run, tmp_path):
    out = tmp_path / "model.spz"
    res = invoke("export", gaussian_run, "--format", "spz", "--out", out, "--backend", "torch")
    assert res.stderr == ""  # a Gaussian SH model fits SPZ: nothing approximated, nothing to report
    model, p = prims_of(gaussian_run)
    assert spz_header(out) == (b"NGSP", 3, model.num_primitives, SH_DEGREE, 12, 0)
    data = gsply_read_spz(out)
    assert data.means.shape == (model.num_primitives, 3) and data.shN.shape == (model.num_primitives, 15, 3)
    g = Gaussians(p["means"], p["log_scales"], p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True),
                  p["opacity_logits"], p["sh0"][:, 0, :], p["sh_rest"])
    check_spz_against(data, g)


def test_spz_edge_cases_read_back_with_gsply(tmp_path):
    """Negative coordinates, every largest-quaternion component and sign, SH and colours past
    the byte range (clipped), SH degree 2."""
    rng = np.random.default_rng(0)
    n = 400
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    g = Gaussians(rng.uniform(-1500, 1500, (n, 3)).astype(np.float32), rng.uniform(-9, 5, (n, 3)).astype(np.float32),
                  quats, rng.normal(0, 4, n).astype(np.float32), rng.normal(0, 1.5, (n, 3)).astype(np.float32),
                  rng.normal(0, 0.6, (n, 8, 3)).astype(np.float32))
    out = tmp_path / "edge.spz"
    with open(out, "wb") as f:
        write_spz(g, f)
    assert spz_header(out)[:4] == (b"NGSP", 3, n, 2)
    data = gsply_read_spz(out)
    # colours are bytes, f_dc * 0.15 * 255 + 127.5: beyond that range they clip
    clipped = Gaussians(g.means, g.log_scales, g.quats, g.opacity_logits,
                        np.clip(g.sh0, -127.5 / 255 / 0.15, 127.5 / 255 / 0.15), g.sh_rest)
    check_spz_against(data, clipped)
    # a coordinate past 2^11 (a far background Gaussian) costs fractional bits, not the Gaussian
    far = Gaussians(g.means * 10, g.log_scales, g.quats, g.opacity_logits, g.sh0, g.sh_rest)
    with open(out, "wb") as f:
        write_spz(far, f)
    assert spz_header(out)[4] == 9  # |x| < 15000 < 2^14: 23 - 14 fractional bits
    check_spz_against(gsply_read_spz(out), Gaussians(far.means, g.log_scales, g.quats, g.opacity_logits,
                                                    clipped.sh0, g.sh_rest), fractional_bits=9)
    beyond = Gaussians(g.means * 10_000, g.log_scales, g.quats, g.opacity_logits, g.sh0, g.sh_rest)
    assert check_spz_range(far) is None and "24-bit" in check_spz_range(beyond)


def render_psnr(model, scene) -> float:
    bg = torch.tensor(scene.background, dtype=torch.float32)
    torch_backend = backends.get("torch")
    with torch.no_grad():
        vals = [float(psnr(model.render(cam, bg, backend=torch_backend).image.clamp(0, 1), cam.image_float()))
                for cam in scene.test]
    return sum(vals) / len(vals)


def test_beta_export_reports_the_measured_psnr_change(beta_run, tmp_path):
    out = tmp_path / "beta.ply"
    res = invoke("export", beta_run, "--format", "ply", "--out", out, "--backend", "torch", "--json")
    doc = json.loads(res.stdout)
    approx = doc["approximation"]
    assert doc["path"] == str(out) and doc["format"] == "ply"
    assert approx["changes"] == ["beta kernel approximated by Gaussians"] and approx["num_views"] == 2
    line = res.stderr.strip()
    assert line == f"splatk export: {approx['message']}"
    assert line.startswith("splatk export: beta kernel approximated by Gaussians: test PSNR ")
    assert f"{approx['psnr_model']:.2f} -> {approx['psnr_export']:.2f} dB ({approx['psnr_change']:+.2f} dB" in line

    # the two renders, redone here: the model as fitted, and a Gaussian model made from the PLY's columns
    model, meta = load_model(beta_run / "model.pt")
    scene = load_scene(meta["scene"], test_every=meta["test_every"], background=tuple(meta["background"]))
    v = PlyData.read(str(out))["vertex"].data
    col = lambda *names: torch.from_numpy(np.stack([v[name] for name in names], 1).copy())  # noqa: E731
    rest = [f"f_rest_{i}" for i in range(45)]
    prims = {"means": col("x", "y", "z"), "log_scales": col("scale_0", "scale_1", "scale_2"),
             "quats": col("rot_0", "rot_1", "rot_2", "rot_3"), "opacity_logits": col("opacity")[:, 0],
             "sh0": col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
             "sh_rest": col(*rest).reshape(-1, 3, 15).transpose(1, 2).contiguous()}
    from_file = SplatModel(make_kernel("gaussian"), make_color_model("sh", sh_degree=SH_DEGREE), prims)
    psnr_model, psnr_file = render_psnr(model, scene), render_psnr(from_file, scene)
    assert psnr_model != pytest.approx(psnr_file, abs=1e-3)  # the kernel change shows in the renders
    assert approx["psnr_model"] == pytest.approx(psnr_model, abs=1e-4)
    assert approx["psnr_export"] == pytest.approx(psnr_file, abs=1e-4)
    assert approx["psnr_change"] == pytest.approx(psnr_file - psnr_model, abs=2e-4)


@pytest.mark.parametrize("fmt", ["splat", "spz"])
def test_beta_export_warns_in_every_gaussian_format(beta_run, tmp_path, fmt):
    res = invoke("export", beta_run, "--format", fmt, "--out", tmp_path / f"beta.{fmt}", "--backend", "torch")
    assert res.stderr.startswith("splatk export: beta kernel approximated by Gaussians")
    assert math.isfinite(float(res.stderr.split("dB (")[1].split(" dB")[0]))


def test_approximation_without_the_scene_says_so(beta_run, root, tmp_path):
    """A run whose scene moved: the file is written and the line says the change was not
    measured; --scene measures it again."""
    obj = torch.load(beta_run / "model.pt", weights_only=False)
    obj["meta"]["scene"] = str(tmp_path / "moved")
    (tmp_path / "run").mkdir()
    torch.save(obj, tmp_path / "run" / "model.pt")
    out = tmp_path / "a.splat"
    res = invoke("export", tmp_path / "run", "--format", "splat", "--out", out, "--backend", "torch", "--json")
    assert out.stat().st_size == 32 * len(obj["prims"]["means"])
    approx = json.loads(res.stdout)["approximation"]
    assert approx["psnr_change"] is None and "not found; pass --scene" in approx["not_measured"]
    assert "test PSNR not measured" in res.stderr
    res = invoke("export", tmp_path / "run", "--format", "splat", "--out", out, "--backend", "torch", "--json",
                 "--overwrite", "--scene", root / "scene")
    assert json.loads(res.stdout)["approximation"]["psnr_change"] is not None


def test_planar_models_are_refused(root, tmp_path):
    run = fit(root, "planar", "--primitive", "planar", "--sh-degree", 0)
    for fmt, name in (("splat", ".splat"), ("spz", "SPZ")):
        res = CliRunner().invoke(cli, ["export", str(run), "--format", fmt, "--out", str(tmp_path / f"m.{fmt}")])
        assert res.exit_code == 2 and f"{name} export of planar (surfel) models is not supported" in res.output
        assert len(res.output.strip().splitlines()) == 1 and not (tmp_path / f"m.{fmt}").exists()
