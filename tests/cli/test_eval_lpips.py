"""`splatk eval --metrics psnr,ssim,lpips`: LPIPS through the CLI; without its weights, asking for it
is an error (exit 2, one line naming the command that installs them)."""
from __future__ import annotations

import importlib
import json
import math

import pytest
from click.testing import CliRunner

from splatk.data.synthetic import make_demo_scene
from splatk.metrics import lpips_available
from splatk.metrics.lpips import ENV_VAR, INSTALL_COMMAND
from splatk.stages.fit import FitConfig, run_fit
from splatk.train.trainer import TrainConfig
from splatk_cli.main import cli

lpips_module = importlib.import_module("splatk.metrics.lpips")  # the package's `lpips` is the function


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval_lpips")
    scene = make_demo_scene(tmp / "scene", num_views=8, size=32)
    cfg = FitConfig(sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=20, budget=200, init="random", backend="torch"))
    return run_fit(scene, tmp / "run", cfg).path


def _eval(run, *extra, env=None):
    res = CliRunner().invoke(cli, ["eval", str(run), "--metrics", "psnr,ssim,lpips", "--backend", "torch", *extra],
                             env=env, catch_exceptions=False)
    return res, json.loads((run / "metrics.json").read_text())


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_eval_reports_lpips(run, net):
    if not lpips_available(net):
        pytest.skip(f"LPIPS {net} weights not installed")
    res, m = _eval(run, "--lpips-net", net)
    assert res.exit_code == 0, res.output
    assert m["lpips_net"] == net
    assert 0.0 < m["mean"]["lpips"] < 1.0
    assert all(0.0 < v["lpips"] < 1.0 for v in m["per_view"])
    assert m["warnings"] == []
    assert "LPIPS" in res.output


def _one_line_error(res) -> str:
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("splatk: error: "), res.stderr
    return lines[0]


def test_missing_weights_stop_eval_naming_the_install_command(run, tmp_path):
    empty = tmp_path / "no_weights"
    empty.mkdir()
    before = (run / "metrics.json").read_text() if (run / "metrics.json").exists() else None
    res = CliRunner().invoke(cli, ["eval", str(run), "--metrics", "psnr,lpips", "--backend", "torch"],
                             env={ENV_VAR: str(empty)}, catch_exceptions=False)
    line = _one_line_error(res)
    assert str(empty / "alexnet.ckpt") in line and "LPIPS-alex weights not found" in line
    assert INSTALL_COMMAND in line
    after = (run / "metrics.json").read_text() if (run / "metrics.json").exists() else None
    assert after == before, "a refused eval rewrote metrics.json"
    # the other metrics do not need the weights
    res = CliRunner().invoke(cli, ["eval", str(run), "--metrics", "psnr,ssim", "--backend", "torch"],
                             env={ENV_VAR: str(empty)}, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    m = json.loads((run / "metrics.json").read_text())
    assert math.isfinite(m["mean"]["psnr"]) and 0.0 < m["mean"]["ssim"] <= 1.0


def test_no_weights_location_at_all(run, monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    monkeypatch.setattr(lpips_module, "weights_path", lambda net, weights_dir=None: None)
    res = CliRunner().invoke(cli, ["eval", str(run), "--metrics", "lpips", "--lpips-net", "vgg", "--backend", "torch"],
                             catch_exceptions=False)
    line = _one_line_error(res)
    assert "LPIPS-vgg weights not found" in line and INSTALL_COMMAND in line


def test_unreadable_weights(run, tmp_path):
    (tmp_path / "alexnet.ckpt").write_bytes(b"not a checkpoint")
    res = CliRunner().invoke(cli, ["eval", str(run), "--metrics", "lpips", "--backend", "torch"],
                             env={ENV_VAR: str(tmp_path)}, catch_exceptions=False)
    line = _one_line_error(res)
    assert "LPIPS-alex weights unreadable" in line and str(tmp_path / "alexnet.ckpt") in line
