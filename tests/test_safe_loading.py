"""Loading a file never runs code: crafted pickles fed to every command that reads a torch file.

Each crafted file is written with ``torch.save`` (so it is a real torch zip) and holds an object
whose ``__reduce__`` makes a sentinel folder when unpickled. Every command must answer with exit
code 2 and one ``splatk: error:`` line naming the file, and the sentinel must not exist. Files
splatk writes itself (model, checkpoint, kernel weights) must still load.
"""
from __future__ import annotations

import ast
import io
import os
import pickle
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk.errors import InputError
from splatk.models.io import load_model
from splatk.train.state import numpy_rng_state, set_numpy_rng_state
from splatk_cli.main import cli

FAST = ["--backend", "torch", "-q"]
FIT = ["--iters", "20", "--checkpoint-every", "10", "--budget", "60", "--init", "random", "--seed", "0",
       "--threads", "1", "--sh-degree", "0", *FAST]


class MakesFolder:
    """Unpickling this calls ``os.mkdir(path)``: a stand-in for any code a pickle can run."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (os.mkdir, (self.path,))


def write_crafted(path: Path, sentinel: Path, like: dict | None = None) -> Path:
    """A torch file shaped like ``like`` (a splatk file's top-level keys) plus the payload."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**(like or {}), "payload": MakesFolder(sentinel)}, path)
    return path


def assert_refused(res, path: Path, sentinel: Path) -> str:
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2, res.output
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    assert lines[0].startswith(f"splatk: error: {path}: "), lines[0]
    assert not sentinel.exists(), "loading the file ran its code"
    return lines[0]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[Path, Path]:
    """(scene, run folder) of a 20-iteration fit of the 32 px demo scene."""
    from splatk.data.synthetic import make_demo_scene

    root = tmp_path_factory.mktemp("safe_loading")
    scene = make_demo_scene(root / "scene", num_views=4, size=32)
    run = root / "run"
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(run), *FIT])
    assert res.exit_code == 0, res.output
    return scene, run


@pytest.fixture
def run_copy(demo_run, tmp_path) -> Path:
    return Path(shutil.copytree(demo_run[1], tmp_path / "run"))


# ------------------------------------------------------------------------------- crafted files refused


@pytest.mark.parametrize("args", [["eval", "{run}", "--metrics", "psnr", "--backend", "torch"],
                                  ["export", "{run}", "--format", "ply", "--out", "{tmp}/m.ply"],
                                  ["export", "{run}", "--format", "native", "--out", "{tmp}/m.pt"],
                                  ["export", "{run}", "--format", "renders", "--out", "{tmp}/renders"],
                                  ["export", "{run}", "--format", "kernels", "--out", "{tmp}/kernels"]],
                         ids=["eval", "export-ply", "export-native", "export-renders", "export-kernels"])
def test_crafted_model_is_refused(run_copy, tmp_path, args):
    sentinel = tmp_path / "PWNED"
    model = write_crafted(run_copy / "model.pt", sentinel, {"format": "splatk-model", "version": 1})
    argv = [a.format(run=run_copy, tmp=tmp_path) for a in args]
    line = assert_refused(CliRunner().invoke(cli, argv), model, sentinel)
    assert "older splatk or not a splatk file" in line and "re-run `splatk fit`" in line
    assert not (tmp_path / "m.pt").exists()  # export --format native copies nothing


def test_crafted_plain_pickle_model_is_refused(run_copy, tmp_path):
    """A pickle that is not a torch zip (torch's legacy format) is refused as well."""
    sentinel = tmp_path / "PWNED"
    (run_copy / "model.pt").write_bytes(pickle.dumps({"format": "splatk-model", "x": MakesFolder(sentinel)}))
    res = CliRunner().invoke(cli, ["eval", str(run_copy), "--backend", "torch"])
    assert_refused(res, run_copy / "model.pt", sentinel)


def test_crafted_checkpoint_is_refused_on_resume(run_copy, tmp_path):
    sentinel = tmp_path / "PWNED"
    ckpt = run_copy / "checkpoints" / "last.pt"
    real = torch.load(ckpt, weights_only=True)
    write_crafted(ckpt, sentinel, {k: v for k, v in real.items() if k != "trainer"} | {"trainer": {}})
    res = CliRunner().invoke(cli, ["fit", "--resume", "--out", str(run_copy), "-q"])
    line = assert_refused(res, ckpt, sentinel)
    assert "without --resume" in line


def test_old_format_checkpoint_is_refused_not_loaded_unsafely(run_copy, monkeypatch):
    """A checkpoint of an older splatk (numpy's RNG state as an ndarray) is refused with a fix,
    and torch.load is only ever called with weights_only=True."""
    ckpt = run_copy / "checkpoints" / "last.pt"
    state = torch.load(ckpt, weights_only=True)
    state["trainer"]["numpy_rng"] = np.random.get_state()
    torch.save(state, ckpt)
    calls = []
    real_load = torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    res = CliRunner().invoke(cli, ["fit", "--resume", "--out", str(run_copy), "-q"])
    line = assert_refused(res, ckpt, run_copy / "PWNED")
    assert "written by an older splatk or not a splatk file" in line
    assert calls == [True]


@pytest.mark.parametrize("primitive", ["volumetric", "planar"])
def test_crafted_kernel_weights_are_refused(demo_run, tmp_path, primitive):
    scene, _ = demo_run
    sentinel = tmp_path / "PWNED"
    weights = write_crafted(tmp_path / "kernel.pt", sentinel, {"format": "splatk-learned-kernel"})
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(tmp_path / "run"), "--kernel", "learned",
                                   "--primitive", primitive, "--kernel-weights", str(weights), *FIT])
    line = assert_refused(res, weights, sentinel)
    assert "re-run `splatk pretrain" in line


def test_crafted_lpips_weights_are_refused(tmp_path, monkeypatch):
    """LPIPS weights are pickles too; a crafted one is reported as unreadable and not run."""
    import cv2

    from splatk.metrics.lpips import ENV_VAR, weights_path

    sentinel = tmp_path / "PWNED"
    weights_dir = tmp_path / "lpips"
    weights_dir.mkdir()
    weights_path("alex", weights_dir).write_bytes(pickle.dumps({"x": MakesFolder(sentinel)}))
    monkeypatch.setenv(ENV_VAR, str(weights_dir))
    img = tmp_path / "a.png"
    cv2.imwrite(str(img), np.full((16, 16, 3), 128, np.uint8))
    res = CliRunner().invoke(cli, ["compare", str(img), str(img), "--metrics", "lpips"])
    assert res.exit_code == 0, res.output
    assert "lpips: n/a" in res.output and "refusing" in res.output
    assert not sentinel.exists()


# ------------------------------------------------------------------------------ real files still load


def test_real_model_and_checkpoint_round_trip(run_copy):
    model, meta = load_model(run_copy / "model.pt")
    assert model.num_primitives > 0 and meta["spec"]["kernel"] == "gaussian"
    res = CliRunner().invoke(cli, ["eval", str(run_copy), "--metrics", "psnr", "--backend", "torch"])
    assert res.exit_code == 0, res.output
    before = torch.load(run_copy / "checkpoints" / "last.pt", weights_only=True)["trainer"]
    # the run is complete: resuming loads the checkpoint, trains nothing and writes it again
    res = CliRunner().invoke(cli, ["fit", "--resume", "--out", str(run_copy), "-q"])
    assert res.exit_code == 0, res.output
    after = torch.load(run_copy / "checkpoints" / "last.pt", weights_only=True)["trainer"]
    assert after["it"] == before["it"] == 20
    assert torch.equal(after["numpy_rng"][1], before["numpy_rng"][1])
    assert after["python_rng"] == before["python_rng"]
    for k in before["prims"]:
        assert torch.equal(after["prims"][k], before["prims"][k]), k


def test_learned_kernel_weights_load(demo_run, tmp_path):
    from splatk.kernels.learned import DEFAULT_WEIGHTS

    scene, _ = demo_run
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(tmp_path / "run"), "--kernel", "learned",
                                   "--kernel-weights", str(DEFAULT_WEIGHTS), "--iters", "2", *FIT[2:]])
    assert res.exit_code == 0, res.output
    assert load_model(tmp_path / "run" / "model.pt")[1]["spec"]["kernel"] == "learned"


def test_rng_states_round_trip_through_weights_only_load():
    """numpy's and Python's generator states survive a weights_only load exactly, including
    numpy's cached second Gaussian."""
    np.random.seed(3)
    np.random.normal()  # leaves a cached Gaussian
    random.seed(5)
    random.gauss(0, 1)
    buf = io.BytesIO()
    torch.save({"numpy": numpy_rng_state(), "python": random.getstate()}, buf)
    buf.seek(0)
    back = torch.load(buf, weights_only=True)
    want = (np.random.normal(size=4), np.random.randint(0, 2**30, 4), random.random(), random.gauss(0, 1))
    np.random.seed(0)
    random.seed(0)
    set_numpy_rng_state(back["numpy"])
    version, internal, gauss_next = back["python"]
    random.setstate((version, tuple(internal), gauss_next))
    got = (np.random.normal(size=4), np.random.randint(0, 2**30, 4), random.random(), random.gauss(0, 1))
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)


def test_no_unsafe_deserialisation_in_the_code():
    """Every torch.load in the engine and the CLI passes weights_only=True, and nothing calls
    pickle.load(s), yaml.load / unsafe_load / full_load or np.load(allow_pickle=True)."""
    root = Path(__file__).resolve().parents[1]
    unsafe = {("pickle", "load"), ("pickle", "loads"), ("yaml", "load"), ("yaml", "unsafe_load"),
              ("yaml", "full_load")}
    offenders, torch_loads = [], 0
    for py in [*(root / "src" / "splatk").rglob("*.py"), *(root / "cli").rglob("*.py")]:
        for node in ast.walk(ast.parse(py.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and isinstance(node.func.value, ast.Name)):
                continue
            call = (node.func.value.id, node.func.attr)
            kwargs = {k.arg: k.value for k in node.keywords}
            where = f"{py.relative_to(root)}:{node.lineno}"
            if call == ("torch", "load"):
                torch_loads += 1
                safe = kwargs.get("weights_only")
                if not (isinstance(safe, ast.Constant) and safe.value is True):
                    offenders.append(f"{where} torch.load without weights_only=True")
            elif call in unsafe:
                offenders.append(f"{where} {'.'.join(call)}")
            elif call in (("np", "load"), ("numpy", "load")) and "allow_pickle" in kwargs:
                offenders.append(f"{where} np.load(allow_pickle=...)")
    assert torch_loads >= 1 and not offenders, offenders


def test_refusal_is_an_input_error(tmp_path):
    from splatk.torch_files import load_torch_file

    sentinel = tmp_path / "PWNED"
    path = write_crafted(tmp_path / "x.pt", sentinel)
    with pytest.raises(InputError) as e:
        load_torch_file(path, "re-run `splatk fit`")
    assert e.value.path == path and e.value.fix == "re-run `splatk fit`"
    assert not sentinel.exists()


def test_model_file_without_its_parts_is_an_input_error(run_copy):
    torch.save({"format": "splatk-model", "version": 1}, run_copy / "model.pt")
    res = CliRunner().invoke(cli, ["eval", str(run_copy), "--backend", "torch"])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert res.output.startswith(f"splatk: error: {run_copy / 'model.pt'}: model file is incomplete"), res.output
