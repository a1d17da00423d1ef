"""`splatk fit --primitive planar` through the CLI: fit, eval and export; unsupported pairs are
one-line errors (exit code 2)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from splatk_cli.main import cli


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    from splatk.data.synthetic import make_demo_scene

    return make_demo_scene(tmp_path_factory.mktemp("demo_planar"), num_views=6, size=32)


def test_planar_fit_eval_export(demo, tmp_path):
    run = tmp_path / "run"
    r = CliRunner().invoke(cli, ["fit", str(demo), "--out", str(run), "--primitive", "planar",
                                 "--kernel", "learned", "--iters", "60", "--budget", "300",
                                 "--threads", "1", "-q"])
    assert r.exit_code == 0, r.output
    summary = json.loads((run / "fit.json").read_text())
    assert summary["primitive"] == "planar" and summary["iterations"] == 60
    obj = torch.load(run / "model.pt", weights_only=False)
    assert obj["spec"]["primitive"] == "planar" and obj["prims"]["log_scales"].shape[1] == 2
    r = CliRunner().invoke(cli, ["eval", str(run), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads((run / "metrics.json").read_text())["primitive"] == "planar"
    r = CliRunner().invoke(cli, ["export", str(run), "--format", "ply", "--out", str(tmp_path / "m.ply")])
    assert r.exit_code == 2 and "PLY export of planar" in r.output, r.output
    assert not (tmp_path / "m.ply").exists()
    r = CliRunner().invoke(cli, ["export", str(run), "--format", "kernels", "--out", str(tmp_path / "k")])
    assert r.exit_code == 2 and "kernel plots of planar" in r.output, r.output
    r = CliRunner().invoke(cli, ["export", str(run), "--format", "renders", "--out", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "r" / "path.gif").is_file()


def test_planar_with_volumetric_only_kernel_is_an_input_error(demo, tmp_path):
    r = CliRunner().invoke(cli, ["fit", str(demo), "--out", str(tmp_path / "run"), "--primitive",
                                 "planar", "--kernel", "beta", "--iters", "5", "-q"])
    assert r.exit_code == 2, r.output
    assert "kernel 'beta' has no planar version" in r.output
    assert "Traceback" not in r.output


def test_geometry_terms_on_volumetric_primitives_are_an_input_error(demo, tmp_path):
    for flag in ("--normal-weight", "--distortion-weight"):
        r = CliRunner().invoke(cli, ["fit", str(demo), "--out", str(tmp_path / "run"), flag, "0.05",
                                     "--iters", "5", "-q"])
        assert r.exit_code == 2, r.output
        assert f"splatk: error: {flag} 0.05: is a term of planar primitives" in r.output
        assert "--primitive planar" in r.output and "Traceback" not in r.output
        assert len(r.output.strip().splitlines()) == 1
        assert not (tmp_path / "run").exists()


def test_planar_fit_logs_the_geometry_terms_from_their_scaled_starts(demo, tmp_path):
    import yaml

    run = tmp_path / "run"
    r = CliRunner().invoke(cli, ["fit", str(demo), "--out", str(run), "--primitive", "planar",
                                 "--normal-weight", "0.05", "--distortion-weight", "10", "--iters", "200",
                                 "--budget", "200", "--threads", "1", "-q"])
    assert r.exit_code == 0, r.output
    doc = yaml.safe_load((run / "config.yaml").read_text())
    train = doc["settings"]["train"]
    # 2DGS's starts at 7000 and 3000 of 30k iterations, scaled to 200 iterations
    assert train["normal_from"] == 47 and train["distortion_from"] == 20
    assert train["normal_weight"] == 0.05 and train["distortion_weight"] == 10.0
    assert "scaled to the run length" in doc["sources"]["normal_from"]
    lines = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    last = lines[-1]
    assert last["it"] == 200
    assert isinstance(last["normal_loss"], float) and isinstance(last["distortion_loss"], float)
    assert 0.0 <= last["normal_loss"] <= 2.0 and last["distortion_loss"] >= 0.0
