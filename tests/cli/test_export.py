"""`splatk export` through the CLI on a short fit of the demo scene; every artefact is opened with a
third-party reader and checked against the model it came from: the 3DGS PLY with plyfile (names,
order, dtype, values = the raw parameters), the native file with splatk's own loader, the renders
with cv2 (one PNG per test view, equal to a fresh render) and PIL (GIF frame count)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image
from plyfile import PlyData

from splatk import backends
from splatk.models.io import load_model
from splatk_cli.main import cli

SH_DEGREE = 3  # the 3DGS layout: 3 f_dc + 45 f_rest


def invoke(*args) -> str:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == 0, f"{res.output}\n{res.exception!r}"
    return res.output


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from splatk.data.synthetic import make_demo_scene

    n = torch.get_num_threads()
    root = tmp_path_factory.mktemp("export")
    scene = make_demo_scene(root / "scene", num_views=9, size=32)  # 7 train, 2 test views
    invoke("fit", scene, "--out", root / "run", "--iters", "60", "--budget", "200", "--init", "random",
           "--sh-degree", SH_DEGREE, "--backend", "torch", "--seed", "2", "-q")
    torch.set_num_threads(n)
    return root / "run"


def test_ply_is_standard_3dgs(run, tmp_path):
    out = tmp_path / "model.ply"
    assert "wrote" in invoke("export", run, "--format", "ply", "--out", out)
    ply = PlyData.read(str(out))
    assert ply.elements[0].name == "vertex" and not ply.text and ply.byte_order == "<"
    v = ply["vertex"].data
    rest = 3 * ((SH_DEGREE + 1) ** 2 - 1)
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(rest)] + ["opacity", "scale_0", "scale_1", "scale_2"]
                + [f"rot_{i}" for i in range(4)])
    assert list(v.dtype.names) == expected
    assert all(v.dtype[name] == np.float32 for name in expected)

    model, _ = load_model(run / "model.pt")
    p = {k: t.detach().numpy() for k, t in model.prims.items()}
    n = model.num_primitives
    assert len(v) == n
    col = lambda *names: np.stack([v[name] for name in names], axis=1)  # noqa: E731
    np.testing.assert_array_equal(col("x", "y", "z"), p["means"])
    np.testing.assert_array_equal(col("nx", "ny", "nz"), np.zeros((n, 3), np.float32))
    np.testing.assert_array_equal(col("f_dc_0", "f_dc_1", "f_dc_2"), p["sh0"][:, 0, :])
    # f_rest is channel-major as 3DGS writes it: all R coefficients, then G, then B
    f_rest = col(*[f"f_rest_{i}" for i in range(rest)]).reshape(n, 3, rest // 3)
    np.testing.assert_array_equal(f_rest, p["sh_rest"].transpose(0, 2, 1))
    np.testing.assert_array_equal(v["opacity"], p["opacity_logits"])
    np.testing.assert_allclose(col("scale_0", "scale_1", "scale_2"), p["log_scales"], atol=1e-6)  # Gaussian: x1
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(col("rot_0", "rot_1", "rot_2", "rot_3"), q, atol=1e-6)
    # what viewers do with the raw values: sigmoid opacity in (0, 1), exp scale > 0, unit quaternions
    assert np.all(np.isfinite(col(*expected)))
    assert np.allclose(np.linalg.norm(col("rot_0", "rot_1", "rot_2", "rot_3"), axis=1), 1, atol=1e-5)


def test_native_reloads(run, tmp_path):
    out = tmp_path / "copy" / "model.pt"
    invoke("export", run, "--format", "native", "--out", out)
    a, meta_a = load_model(run / "model.pt")
    b, meta_b = load_model(out)
    assert meta_a == meta_b and b.kernel.name == a.kernel.name and b.color.name == a.color.name
    for k in a.prims:
        assert torch.equal(a.prims[k], b.prims[k]), k


def test_renders_and_gif(run, tmp_path):
    from splatk.data import load_scene

    out = tmp_path / "renders"
    invoke("export", run, "--format", "renders", "--out", out, "--backend", "torch")
    model, meta = load_model(run / "model.pt")
    scene = load_scene(meta["scene"], test_every=meta["test_every"], background=tuple(meta["background"]))
    pngs = sorted(out.glob("*.png"))
    assert [p.stem for p in pngs] == sorted(c.name.split("/")[-1].split(".")[0] for c in scene.test)
    bg = torch.tensor(scene.background)
    for cam in scene.test:
        img = cv2.imread(str(out / f"{cam.name.split('/')[-1].split('.')[0]}.png"), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
        with torch.no_grad():
            ref = model.render(cam, bg, backend=backends.get("torch")).image.clamp(0, 1).numpy()
        diff = np.abs(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255 - ref)
        assert diff.max() <= 1 / 255 + 1e-6  # 8-bit rounding only
    with Image.open(out / "path.gif") as gif:
        assert gif.format == "GIF" and gif.size == (32, 32)
        frames = gif.n_frames
        assert frames == 48  # export_renders' gif_frames
        gif.seek(frames - 1)
        assert np.asarray(gif.convert("RGB")).std() > 0  # a picture, not a blank frame
