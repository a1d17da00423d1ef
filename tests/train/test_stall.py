"""Recovery is bounded: rollbacks that keep failing from the same healthy state stop the fit
(TrainingStalled; `splatk fit` exits 3) and the run keeps its last healthy state."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import synthetic_scene  # noqa: E402

from splatk.data.synthetic import make_demo_scene
from splatk.errors import TrainingStalled
from splatk.models.volumetric import SplatModel
from splatk.train import trainer as trainer_module
from splatk.train.guard import MAX_ROLLBACKS_WITHOUT_PROGRESS
from splatk.train.trainer import TrainConfig, Trainer
from splatk_cli.main import cli


def always_nan(*args, **kwargs):
    return torch.tensor(float("nan"))


def test_rollbacks_that_never_help_stop_the_fit(monkeypatch):
    scene = synthetic_scene(num_views=8)
    model = SplatModel.from_points(scene.points, scene.point_colors, color_options={"sh_degree": 1})
    tr = Trainer(scene, model, TrainConfig(iters=10_000, budget=100, backend="torch", snapshot_every=10))
    tr.run(should_stop=lambda: tr.it >= 20)
    healthy = {k: v.detach().clone() for k, v in tr.model.prims.items()}
    monkeypatch.setattr(trainer_module, "photometric_loss", always_nan)
    with pytest.raises(TrainingStalled) as err:
        tr.run()
    assert "non-finite" in str(err.value) and "likely cause" in str(err.value)
    rollbacks = [e for e in tr.events if e["event"] == "nan_rollback"]
    assert len(rollbacks) == MAX_ROLLBACKS_WITHOUT_PROGRESS  # bounded, not forever
    assert tr.it < 20 + MAX_ROLLBACKS_WITHOUT_PROGRESS + 2
    tr.restore_last_healthy()
    assert tr.it == 20
    for k, v in healthy.items():
        assert torch.equal(tr.model.prims[k], v), k


def test_fit_exits_3_and_keeps_the_last_healthy_checkpoint(tmp_path, monkeypatch):
    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    monkeypatch.setattr(trainer_module, "photometric_loss", always_nan)
    out = tmp_path / "run"
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(out), "--iters", "50", "--budget", "100",
                                   "--backend", "torch", "--threads", "1", "-q"])
    assert res.exit_code == 3, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert lines[-1].startswith("splatk: error: ") and "training stalled" in lines[-1]
    assert "checkpoints" in lines[-1] and "Traceback" not in res.output
    state = torch.load(out / "checkpoints" / "last.pt", weights_only=True)
    assert state["trainer"]["it"] == 0  # the initial state: nothing after it was healthy
    assert all(torch.isfinite(v).all() for v in state["trainer"]["prims"].values())
    assert not (out / "model.pt").exists()  # a stalled run is not a finished one
