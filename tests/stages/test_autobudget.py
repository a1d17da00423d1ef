"""`--budget auto`: short runs judged on held-out train views, stop rule, refit, compaction, prune,
report in fit.json."""
from __future__ import annotations

import json

import pytest
import torch

from splatk import backends
from splatk.data import load_scene
from splatk.data.synthetic import make_demo_scene
from splatk.stages.autobudget import (AutoBudget, AutoBudgetConfig, blending_weights, compaction_cut,
                                     render_psnr, split_holdout)
from splatk.stages.fit import FitConfig, build_model, run_fit
from splatk.train.mcmc import MCMCConfig
from splatk.train.trainer import TrainConfig, Trainer
from splatk.stages.fit_config import fit_config_from_options


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("auto") / "demo", num_views=8, size=32)


def _cfg(threshold: float) -> FitConfig:
    # base 400 -> budgets 50, 100, 200, 400; a short run of 20 iterations each, growing 5% per
    # iteration (refine_every 1) so that every run can reach its budget
    auto = AutoBudgetConfig(start_fraction=0.125, max_factor=1.0, threshold_db=threshold, stage_share=0.2)
    train = TrainConfig(iters=100, budget=400, init="random", backend="torch",
                        mcmc=MCMCConfig(refine_every=1, refine_start=0))
    return FitConfig(sh_degree=1, backend="torch", threads=1, auto_budget=auto, train=train)


def test_stops_growing_when_a_doubling_gains_too_little(scene, tmp_path):
    run = run_fit(scene, tmp_path / "run", _cfg(threshold=100.0)).path
    rep = json.loads((run / "fit.json").read_text())["auto_budget"]
    assert rep["budgets_planned"] == [50, 100, 200, 400]
    assert [s["budget"] for s in rep["stages"]] == [50, 100]
    # the doubled budget's short run did grow further than the first one...
    assert rep["stages"][1]["num_primitives"] > 1.5 * rep["stages"][0]["num_primitives"]
    assert rep["chosen_budget"] == 50  # ...but gained < 100 dB, so back to the 50 model
    assert "gained" in rep["stopped_because"]
    assert rep["holdout_views"] and rep["holdout_returned_to_training"]
    assert rep["prune"]["num_primitives_before"] <= 50
    summary = json.loads((run / "fit.json").read_text())
    assert summary["num_primitives"] == rep["prune"]["num_primitives_after"] <= 50
    assert summary["iterations"] == 100
    assert summary["train_views"] == 7  # the held-out view went back to the optimiser


def test_keeps_doubling_while_it_pays(scene, tmp_path):
    result = run_fit(scene, tmp_path / "run", _cfg(threshold=-100.0))
    rep = json.loads((result.path / "fit.json").read_text())["auto_budget"]
    assert result.summary["auto_budget"] == rep  # what run_fit returns is what it wrote
    assert rep["chosen_budget"] == 400
    assert [s["budget"] for s in rep["stages"]] == [50, 100, 200, 400]
    assert all(s["gain_db"] is not None for s in rep["stages"][1:])
    assert json.loads((result.path / "fit.json").read_text())["num_primitives"] <= 400


def test_blending_weights_add_up_to_the_rendered_alpha(scene):
    """Each pixel's alpha is the sum of its primitives' weights T * alpha, so the weights summed
    over primitives are the alpha maps summed over pixels and views."""
    sc, tr = _trained(scene, iters=20)
    backend = backends.get("torch")
    w = blending_weights(tr.model, sc.train, backend)
    with torch.no_grad():
        alpha = sum(float(tr.model.render(c, torch.zeros(3), backend=backend).alpha.sum()) for c in sc.train)
    assert w.shape == (tr.model.num_primitives,) and (w >= 0).all()
    assert float(w.sum()) == pytest.approx(alpha, rel=1e-4)


def test_settings_of_the_superseded_selection_modes():
    """config.yaml files that name the short runs and the refit still load; a removed mode is
    refused with a message that says what to drop."""
    old = AutoBudgetConfig.from_dict({"selection": "short_runs", "refit": True, "paired": True,
                                      "return_holdout": True, "threshold_db": 0.3})
    assert old == AutoBudgetConfig(threshold_db=0.3)
    with pytest.raises(ValueError, match="no longer available"):
        AutoBudgetConfig.from_dict({"selection": "stages"})
    with pytest.raises(ValueError, match="no longer available"):
        AutoBudgetConfig.from_dict({"refit": False})


def test_prune_drops_invisible_and_transparent_primitives(scene):
    sc = load_scene(scene)
    cfg = FitConfig(sh_degree=1, backend="torch", train=TrainConfig(budget=60, init="random", backend="torch"))
    tr = Trainer(sc, build_model(sc, cfg), cfg.train)
    tr.run(should_stop=lambda: tr.it >= 3)  # Adam moments exist
    n = tr.model.num_primitives
    rows = {k: v.data[:6].clone() for k, v in tr.model.prims.items()}
    rows["means"][:3] = 1e4  # far outside every view
    rows["opacity_logits"][3:] = -20.0  # transparent
    tr.opt.append_rows(rows)
    w = blending_weights(tr.model, sc.train, backend=backends.get("torch"))
    assert (w[n:n + 3] == 0).all() and (w[:n] > 0).any()
    ab = AutoBudget(AutoBudgetConfig(), 60)
    rep = ab.prune(tr, sc.train[:1])
    assert rep["pruned"] >= 6 and tr.model.num_primitives <= n
    assert rep["low_opacity"] >= 3 and rep["below_weight"] >= 3
    assert not (tr.model.prims["means"] > 1e3).any()
    tr.cfg.iters = tr.it + 2
    tr.run()  # the optimiser still lines up with the pruned tensors


def _trained(scene, budget=120, iters=60):
    sc = load_scene(scene)
    cfg = FitConfig(sh_degree=1, backend="torch", train=TrainConfig(iters=iters, budget=budget, init="random",
                                                                     backend="torch", mcmc=MCMCConfig(refine_every=5)))
    tr = Trainer(sc, build_model(sc, cfg), cfg.train)
    tr.run()
    return sc, tr


@pytest.mark.parametrize("tolerance", [0.05, 0.5])
def test_compaction_keeps_the_fewest_top_contributors_within_the_tolerance(scene, tolerance):
    """The cut keeps the most contributing primitives, as few as hold the PSNR on the views within
    the tolerance: rendering the kept ones gives a drop within it, and one grid step fewer does not."""
    sc, tr = _trained(scene)
    model, bg = tr.model, torch.tensor(sc.background, dtype=torch.float32)
    n, steps, min_keep = model.num_primitives, 10, 0.2
    keep, rep = compaction_cut(model, sc.train, bg, tolerance, min_keep, backends.get("torch"), steps=steps)
    assert model.num_primitives == n  # the model itself is untouched
    base = render_psnr(model, sc.train, bg, backends.get("torch"))
    assert rep["train_psnr_before"] == pytest.approx(base)
    k = int(keep.sum())
    assert k == rep["num_primitives_after"] and k < n  # random init leaves dead weight
    w = blending_weights(model, sc.train, backends.get("torch"))
    assert w[keep].min() >= w[~keep].max()  # the kept ones are the top contributors

    def psnr_of(mask):
        full = {key: v.data for key, v in model.prims.items()}
        for key, v in model.prims.items():
            v.data = full[key][mask]
        try:
            return render_psnr(model, sc.train, bg, backends.get("torch"))
        finally:
            for key, v in model.prims.items():
                v.data = full[key]

    assert base - psnr_of(keep) <= tolerance + 1e-6
    grid = [min_keep + (1 - min_keep) * i / steps for i in range(steps + 1)]
    i = min(range(len(grid)), key=lambda j: abs(grid[j] * n - k))
    if i > 0:  # one step fewer breaks the tolerance
        fewer = torch.zeros(n, dtype=torch.bool)
        fewer[torch.argsort(w, descending=True)[:int(round(n * grid[i - 1]))]] = True
        assert base - psnr_of(fewer) > tolerance


def test_fit_compacts_once_growth_ends_and_fine_tunes_without_regrowing(scene, tmp_path):
    cfg = _cfg(threshold=100.0)  # chooses 50
    cfg.auto_budget.compact_tolerance_db = 1.0
    summary = run_fit(scene, tmp_path / "run", cfg).summary
    comp = summary["auto_budget"]["compact"]
    assert comp["iteration"] == 84  # the first iteration at refine_stop (25/30 of 100)
    assert comp["num_primitives_after"] < comp["num_primitives_before"] <= 50
    assert comp["train_psnr_before"] - comp["train_psnr_after"] <= 1.0
    assert summary["auto_budget"]["prune"]["num_primitives_before"] == comp["num_primitives_after"]
    assert summary["num_primitives"] <= comp["num_primitives_after"]
    assert any(e["event"] == "compacted" for e in summary["events"])


def test_holdout_never_takes_all_views():
    cams = list(range(7))
    train, held = split_holdout(cams, 8)
    assert held and train and set(train) | set(held) == set(cams) and not set(train) & set(held)


def test_cli_budget_auto_parses():
    def build_fit_config(options):
        return fit_config_from_options(options)[0]

    cfg = build_fit_config({"budget": "auto"})
    assert cfg.auto_budget is not None and cfg.train.budget == TrainConfig().budget
    assert build_fit_config({"budget": "5000"}).auto_budget is None
    ref = build_fit_config({"budget": "auto:8000"})
    assert ref.auto_budget is not None and ref.train.budget == 8000


def test_resume_mid_selection_continues_the_short_runs(scene, tmp_path):
    cfg = _cfg(threshold=-100.0)
    # a run stopped inside the second short run (Ctrl-C / SIGTERM path), then resumed
    part = tmp_path / "part"
    calls = {"n": 0}

    def stop():
        calls["n"] += 1
        return calls["n"] >= 30

    run_fit(scene, part, cfg, should_stop=stop)
    first = json.loads((part / "fit.json").read_text())
    assert first["iterations"] < 100 and first["auto_budget"]["chosen_budget"] is None
    run_fit(scene, part, cfg, resume=True)
    rep = json.loads((part / "fit.json").read_text())
    assert rep["iterations"] == 100
    assert [s["budget"] for s in rep["auto_budget"]["stages"]] == [50, 100, 200, 400]
    assert rep["auto_budget"]["chosen_budget"] == 400 and rep["auto_budget"]["prune"] is not None


def test_random_init_starts_at_a_quarter_of_the_budget(scene):
    """Random points start at a quarter of the budget so that MCMC grows the model (the growth
    carries primitives out of the init box); --budget auto starts at its first stage's budget,
    and an explicit random_points wins."""
    sc = load_scene(scene)
    plain = FitConfig(sh_degree=1, backend="torch", train=TrainConfig(budget=400, init="random"))
    assert build_model(sc, plain).num_primitives == 100
    assert plain.train.random_points is None  # the rule, not a number, is the setting
    auto = _cfg(threshold=0.0)
    assert build_model(sc, auto, budget=50).num_primitives == 50
    fixed = FitConfig(sh_degree=1, backend="torch", train=TrainConfig(budget=400, init="random", random_points=300))
    assert build_model(sc, fixed).num_primitives == 300


def test_refit_is_the_fixed_run_at_the_chosen_budget(scene, tmp_path):
    """Once chosen, --budget auto trains a fresh model at the chosen budget on every train view,
    exactly as `--budget N` would: same parameters, the selection's time added to the run's."""
    cfg = _cfg(threshold=100.0)  # chooses 50
    cfg.auto_budget.prune_opacity, cfg.auto_budget.prune_weight = 0.0, -1.0  # prune nothing
    cfg.auto_budget.compact = False
    auto_run = run_fit(scene, tmp_path / "auto", cfg).path
    rep = json.loads((auto_run / "fit.json").read_text())
    assert rep["auto_budget"]["chosen_budget"] == 50 and rep["auto_budget"]["refit"]
    fixed_cfg = _cfg(threshold=100.0)
    fixed_cfg.auto_budget = None
    fixed_cfg.train.budget = 50
    fixed_run = run_fit(scene, tmp_path / "fixed", fixed_cfg).path
    fixed = json.loads((fixed_run / "fit.json").read_text())
    assert rep["train_views"] == fixed["train_views"] == 7
    assert rep["initial_psnr"] == pytest.approx(fixed["initial_psnr"])
    a = torch.load(auto_run / "model.pt", weights_only=True)
    b = torch.load(fixed_run / "model.pt", weights_only=True)
    pa, pb = a["prims"], b["prims"]
    assert set(pa) == set(pb)
    for key in pa:
        torch.testing.assert_close(pa[key], pb[key], rtol=0, atol=0)
    sel = rep["auto_budget"]["selection_seconds"]
    assert sel > 0 and rep["train_seconds"] == pytest.approx(fixed["train_seconds"] + sel, rel=0.5)


def test_resume_inside_the_refit_gives_the_uninterrupted_result(scene, tmp_path):
    cfg = _cfg(threshold=100.0)
    whole = torch.load(run_fit(scene, tmp_path / "whole", cfg).path / "model.pt", weights_only=True)
    calls = {"n": 0}

    def stop():  # the selection (short runs at 50 and 100, 20 steps each) ends before 70 checks
        calls["n"] += 1
        return calls["n"] >= 70

    part = tmp_path / "part"
    run_fit(scene, part, cfg, should_stop=stop)
    state = torch.load(part / "checkpoints" / "last.pt", weights_only=True)
    assert state["auto_budget"]["refitting"] and 0 < state["trainer"]["it"] < 100
    run_fit(scene, part, cfg, resume=True)
    resumed = torch.load(part / "model.pt", weights_only=True)
    for key in whole["prims"]:
        torch.testing.assert_close(resumed["prims"][key], whole["prims"][key], rtol=1e-5, atol=1e-6)


def test_short_runs_selection_trains_each_budget_from_the_start(scene, tmp_path):
    cfg = _cfg(threshold=-100.0)
    rep = run_fit(scene, tmp_path / "run", cfg).summary
    ab = rep["auto_budget"]
    assert ab["selection"] == "short_runs" and ab["refit"]
    # base 400, stages of 0.2 -> four budgets, each a complete run of 20 iterations
    assert [s["budget"] for s in ab["stages"]] == [50, 100, 200, 400]
    assert all(s["iteration"] == 20 for s in ab["stages"])
    assert ab["selection_iterations"] == 80
    st = ab["stages"]
    for prev, cur in zip(st, st[1:]):
        assert cur["gain_db"] == pytest.approx(cur["holdout_psnr"] - prev["holdout_psnr"])
    assert ab["chosen_budget"] == 400 and rep["iterations"] == 100
    assert rep["train_seconds"] > ab["selection_seconds"] > 0


def test_resume_inside_a_short_run_gives_the_uninterrupted_result(scene, tmp_path):
    cfg = _cfg(threshold=100.0)  # 50, then 100: gains < 100 dB, so 50 is refit
    whole_dir = run_fit(scene, tmp_path / "whole", cfg).path
    whole = json.loads((whole_dir / "fit.json").read_text())["auto_budget"]
    steps = {"n": 0}

    def count(info):
        steps["n"] += 1

    part = tmp_path / "part"  # stopped 8 steps into the second short run (each takes 20)
    run_fit(scene, part, cfg, on_step=count, should_stop=lambda: steps["n"] >= 28)
    state = torch.load(part / "checkpoints" / "last.pt", weights_only=True)
    assert state["auto_budget"]["current_short"] == 100 and 0 < state["trainer"]["it"] < 20
    run_fit(scene, part, cfg, resume=True)
    rep = json.loads((part / "fit.json").read_text())["auto_budget"]
    assert rep["chosen_budget"] == whole["chosen_budget"] == 50
    for a, b in zip(rep["stages"], whole["stages"]):
        assert a["holdout_psnr"] == pytest.approx(b["holdout_psnr"], abs=1e-3)
    a = torch.load(part / "model.pt", weights_only=True)["prims"]
    b = torch.load(whole_dir / "model.pt", weights_only=True)["prims"]
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-5, atol=1e-6)


def test_resume_after_the_compaction_gives_the_uninterrupted_result(scene, tmp_path):
    """A run stopped during the fine-tuning that follows the compaction resumes with the
    compacted model (not compacting again) and ends where the uninterrupted run does."""
    cfg = _cfg(threshold=100.0)
    cfg.auto_budget.compact_tolerance_db = 1.0
    whole_run = run_fit(scene, tmp_path / "whole", cfg).path
    whole = torch.load(whole_run / "model.pt", weights_only=True)
    calls = {"n": 0}

    def stop():  # the selection takes 40 checks; the refit compacts at its iteration 84
        calls["n"] += 1
        return calls["n"] >= 130

    part = tmp_path / "part"
    run_fit(scene, part, cfg, should_stop=stop)
    state = torch.load(part / "checkpoints" / "last.pt", weights_only=True)
    assert state["auto_budget"]["compact_report"] is not None and 84 <= state["trainer"]["it"] < 100
    run_fit(scene, part, cfg, resume=True)
    resumed = torch.load(part / "model.pt", weights_only=True)
    for key in whole["prims"]:
        torch.testing.assert_close(resumed["prims"][key], whole["prims"][key], rtol=1e-5, atol=1e-6)
    a = json.loads((part / "fit.json").read_text())["auto_budget"]["compact"]
    b = json.loads((whole_run / "fit.json").read_text())["auto_budget"]["compact"]
    assert a == b
