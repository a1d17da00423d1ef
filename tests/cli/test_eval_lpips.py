"""`splatk eval --metrics psnr,ssim,lpips`: LPIPS through the CLI, and missing weights."""
from __future__ import annotations

import json
import math

import pytest
from click.testing import CliRunner

from splatk.data.synthetic import make_demo_scene
from splatk.metrics import lpips_available
from splatk.metrics.lpips import ENV_VAR
from splatk.stages.fit import FitConfig, run_fit
from splatk.train.trainer import TrainConfig
from splatk_cli.main import cli


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


def test_missing_weights_warn_and_keep_other_metrics(run, tmp_path):
    empty = tmp_path / "no_weights"
    empty.mkdir()
    res, m = _eval(run, env={ENV_VAR: str(empty)})
    assert res.exit_code == 0, res.output
    assert "warning" in res.stderr and "LPIPS-alex weights not found" in res.stderr
    assert m["mean"]["lpips"] is None
    assert math.isfinite(m["mean"]["psnr"]) and 0.0 < m["mean"]["ssim"] <= 1.0
    assert m["warnings"] and str(empty) in m["warnings"][0]
