"""The paper's protocols as `splatk bench` presets: each grid runs (two iterations here, on a tiny
generated scene), each is the paper's protocol as written (30k iterations, schedules unscaled)
and says so when shortened, and the pretraining a method asks for happens once per shape."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml
from click.testing import CliRunner

from splatk.bench import fit_config_for, load_bench_file
from splatk.data.synthetic import make_demo_scene
from splatk.stages import pretrain as pretrain_stage
from splatk_cli.common import find_preset
from splatk_cli.main import cli

PRESETS = ("paper_tab1", "paper_tab2", "paper_tab3_4", "paper_tab5")


@pytest.mark.parametrize("name", PRESETS)
def test_preset_is_the_papers_protocol(name):
    data = load_bench_file(find_preset(name))
    assert data["defaults"]["iters"] == 30000 and data["scale_schedules"] is False
    assert data["protocol"]["iters"] == 30000
    for method in data["methods"]:
        cfg, notes = fit_config_for(method, data["defaults"], scale_schedules=False)
        assert cfg.train.iters == 30000 and "scaled_schedules" not in notes
        assert cfg.train.mcmc.refine_every == 100 and cfg.train.sh_degree_interval == 1000
        if cfg.kernel == "learned" and cfg.primitive == "volumetric":
            assert cfg.kernel_options.get("freeze_iters", 2000) == 2000  # the paper's freeze
    if name == "paper_tab2":
        assert all(fit_config_for(m, data["defaults"], False)[0].sh_degree == 0 for m in data["methods"])


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_demo_scene(tmp_path_factory.mktemp("paper") / "scene", num_views=6, size=16)


def shrunk_preset(name: str, tmp: Path, extra: dict | None = None) -> Path:
    """The preset with its byte budgets and pretraining made tiny (the grid itself unchanged)."""
    data = yaml.safe_load(find_preset(name).read_text())
    if "grid" in data and "budget_bytes" in data["grid"]:
        data["grid"]["budget_bytes"] = ["48KB", "64KB", "96KB"]
    for method in data.get("methods", []) + [data.get("defaults", {})]:
        if "pretrain" in method:
            method["pretrain_steps"] = 3
    for entry in (data.get("grid") or {}).get("kernel", []):
        if isinstance(entry, dict) and "pretrain" in entry:
            entry["pretrain_steps"] = 3
    data["defaults"].update(extra or {})
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def tiny_pretraining(monkeypatch):
    """The bench's pretraining with a tiny first stage too (pretrain_steps shortens the second
    only): the grid's bookkeeping is under test here, not how well the networks fit."""
    real = pretrain_stage.run_pretrain
    tiny = pretrain_stage.PretrainConfig(dec_candidates=2, dec_steps=3, eval_primitives=64)
    monkeypatch.setattr(pretrain_stage, "run_pretrain", lambda *a, **kw: real(*a, config=tiny, **kw))


@pytest.mark.parametrize("name", PRESETS)
def test_two_iteration_grid_runs_and_says_it_is_shortened(name, scene, tmp_path, tiny_pretraining):
    preset = shrunk_preset(name, tmp_path, {"budget": 60} if name != "paper_tab2" else None)
    out = tmp_path / "bench"
    res = CliRunner().invoke(cli, ["bench", str(scene), "--out", str(out), "--preset", str(preset), "--iters", "2",
                                   "--backend", "torch", "--threads", "1", "--metrics", "psnr"])
    assert res.exit_code == 0, res.output
    assert "not paper Tab" in res.output and "iters 2 (protocol: 30000)" in res.output.replace("\n", " ")
    rows = [json.loads(p.read_text()) for p in (out / "results").glob("*.json")]
    data = load_bench_file(preset)
    assert len(rows) == len(data["methods"]) and all(r["status"] == "ok" for r in rows), \
        [r.get("error") for r in rows if r["status"] != "ok"]
    assert all(r["iterations"] == 2 for r in rows)
    if name == "paper_tab3_4":  # one pretraining per network shape, and each fit used its own
        pretrained = sorted((out / "pretrain").glob("*.pt"))
        assert len(pretrained) == len({json.dumps(m.get("kernel_options"), sort_keys=True) for m in data["methods"]})
        by_name = {r["method"]: r for r in rows}
        opts = by_name["z3d-1"]["config"]["kernel_options"]
        assert opts["latent_dim"] == 1 and Path(opts["weights"]).parent == (out / "pretrain").resolve()
        assert torch.load(opts["weights"], weights_only=True)["options"]["latent_dim"] == 1
    if name == "paper_tab2":  # --k auto ran with the k the scene's pixels per primitive chose
        auto = [r for r in rows if "-kauto-" in r["method"]]
        assert len(auto) == 3 and all(r["config"]["kernel_options"]["k"] in (2, 4, 8) for r in auto)
    if name == "paper_tab5":
        assert len(list((out / "pretrain").glob("*.pt"))) == 4  # four targets, shared by k = 2, 4, 8
