"""`splatk bench` engine: results per run, resume without retraining, charts, Pareto front,
byte budgets, the stability matrix and its flags (tiny generated scene, short runs)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from splatk.data.synthetic import make_demo_scene
from splatk.errors import InputError
from splatk.machine import CPU_FEATURES
from splatk.bench import runner
from splatk.bench import (
    BenchConfig,
    BenchStopped,
    classify,
    fit_config_for,
    method_id,
    run_bench,
    run_stability,
)
from splatk.bench.charts import pareto_front
from splatk.stages.fit_memory import bytes_per_primitive
from splatk.stages.fit import run_fit
from tests.data.layouts import write_ply

BASE = {"iters": 40, "budget": 200, "init": "random", "sh_degree": 1, "backend": "torch", "threads": 1}
METHODS = [{"kernel": "gaussian"}, {"kernel": "learned", "k": 2}]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("bench") / "demo", num_views=8, size=32)


@pytest.fixture(scope="module")
def scene_with_points(tmp_path_factory):
    """The demo scene with SfM-like points (``ply_file_path``), so that ``init: auto`` is sfm."""
    root = make_demo_scene(tmp_path_factory.mktemp("bench_points") / "points", num_views=8, size=32)
    rng = np.random.default_rng(0)
    write_ply(root / "points.ply", rng.uniform(-1, 1, (300, 3)), rng.uniform(0, 1, (300, 3)))
    doc = json.loads((root / "transforms_train.json").read_text())
    (root / "transforms_train.json").write_text(json.dumps({**doc, "ply_file_path": "points.ply"}))
    return root


@pytest.fixture(scope="module")
def grid(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_out")
    cfg = BenchConfig(methods=METHODS, defaults=BASE, metrics=("psnr", "ssim"))
    return out, cfg, run_bench([scene], cfg, out)


def _spy_run_fit(monkeypatch):
    calls = []

    def spy(*args, **kwargs):
        calls.append(kwargs.get("resume", False))
        return run_fit(*args, **kwargs)

    monkeypatch.setattr(runner, "run_fit", spy)
    return calls


def test_one_result_json_per_run(grid):
    out, cfg, res = grid
    files = sorted((out / "results").glob("*.json"))
    assert [f.name for f in files] == ["demo__gaussian-sh.json", "demo__learned-k2-sh.json"]
    for f in files:
        r = json.loads(f.read_text())
        assert r["status"] == "ok"
        for key in ("psnr", "ssim", "train_seconds", "render_ms", "footprint_mb", "num_primitives", "config"):
            assert r[key] is not None, key
        assert "lpips" in r and r["threads"] == 1
        # which CPU the figure came from: results are only bit-comparable on the same features
        assert r["machine"]["torch"] == torch.__version__ and r["machine"]["logical_cpus"] >= 1
        assert set(r["machine"]["cpu_features"]) <= set(CPU_FEATURES)
        assert r["config"]["train"]["iters"] == 40 and r["num_primitives"] <= 200
        assert (out / "runs" / "demo" / r["method"] / "model.pt").is_file()
    assert [r["method"] for r in res.rows] == ["gaussian-sh", "learned-k2-sh"]


def test_second_call_skips_finished_runs(grid, scene, monkeypatch):
    out, cfg, _ = grid
    calls = _spy_run_fit(monkeypatch)
    before = {p: p.stat().st_mtime_ns for p in (out / "results").glob("*.json")}
    model_before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("model.pt")}
    res = run_bench([scene], cfg, out)
    assert calls == []
    assert {p: p.stat().st_mtime_ns for p in (out / "results").glob("*.json")} == before
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("model.pt")} == model_before
    assert len(res.rows) == 2


def test_changed_settings_are_not_mistaken_for_finished(grid, scene):
    out, cfg, _ = grid
    other = BenchConfig(methods=METHODS[:1], defaults={**BASE, "iters": 41}, metrics=("psnr",))
    with pytest.raises(Exception, match="other settings"):
        run_bench([scene], other, out)


def test_charts_exist_and_decode(grid):
    out, _, res = grid
    for stem in ("psnr_vs_render_ms", "psnr_vs_train_seconds", "psnr_vs_footprint_mb"):
        img = cv2.imread(str(out / "charts" / f"{stem}.png"))
        assert img is not None and img.shape[0] > 100 and img.shape[1] > 100
        assert (out / "charts" / f"{stem}.svg").read_text().lstrip().startswith("<?xml")
    assert len(res.charts) == 6


def test_partial_run_resumes_from_checkpoint(scene, tmp_path, monkeypatch):
    cfg = BenchConfig(methods=[{"kernel": "beta"}], defaults=BASE, metrics=("psnr",))
    fit_cfg, _ = fit_config_for(cfg.methods[0], cfg.defaults)
    run = tmp_path / "runs" / "demo" / method_id(cfg.methods[0])
    run_fit(scene, run, fit_cfg, should_stop=lambda: True)  # stops after one iteration
    assert json.loads((run / "fit.json").read_text())["iterations"] == 1
    calls = _spy_run_fit(monkeypatch)
    res = run_bench([scene], cfg, tmp_path)
    assert calls == [True]  # resumed, not started over
    assert res.rows[0]["iterations"] == 40


def _stopped_grid(scene, cfg: BenchConfig, out: Path, polls: int) -> BenchStopped:
    """Run the grid until its stop request has been polled ``polls`` times; the BenchStopped."""
    count = {"n": 0}

    def stop_later():
        count["n"] += 1
        return count["n"] > polls

    with pytest.raises(BenchStopped) as stopped:
        run_bench([scene], cfg, out, should_stop=stop_later)
    return stopped.value


def test_stop_request_keeps_the_checkpoint_and_writes_no_result(scene, tmp_path):
    """A stop request (SIGTERM, Ctrl-C) mid-fit ends the bench without evaluating the unfinished
    run; the next call resumes that fit and finishes the grid."""
    cfg = BenchConfig(methods=[{"kernel": "gaussian"}, {"kernel": "beta"}], defaults=BASE, metrics=("psnr",))
    stopped = _stopped_grid(scene, cfg, tmp_path, polls=15)
    run = tmp_path / "runs" / "demo" / method_id(cfg.methods[0])
    assert stopped.run == run and (run / "checkpoints" / "last.pt").is_file()
    assert 0 < json.loads((run / "fit.json").read_text())["iterations"] < BASE["iters"]
    assert not list((tmp_path / "results").glob("*.json"))  # neither run counts as done
    events = []
    res = run_bench([scene], cfg, tmp_path, on_event=lambda kind, info: events.append((kind, info["method"])))
    assert events[0] == ("resume", method_id(cfg.methods[0])) and ("fit", method_id(cfg.methods[1])) in events
    assert [r["iterations"] for r in res.rows] == [BASE["iters"]] * 2


def test_a_grid_stopped_with_one_placement_goes_on_with_another(scene, tmp_path):
    """Threads, backend and device say where a run executes, not what it is: a stopped cell
    resumes with the values given now (its config records them) instead of starting over, and a
    finished result made with other values is reused, not refused as other settings."""
    methods = [{"kernel": "gaussian"}, {"kernel": "beta"}]
    first = BenchConfig(methods=methods, defaults=BASE, metrics=("psnr",))
    stopped = _stopped_grid(scene, first, tmp_path, polls=60)  # in the second run
    assert stopped.run == tmp_path / "runs" / "demo" / method_id(methods[1])
    done_before = json.loads((stopped.run / "fit.json").read_text())["iterations"]
    assert 0 < done_before < BASE["iters"]
    elsewhere = BenchConfig(methods=methods, defaults={**BASE, "threads": 2, "backend": "auto"},
                            metrics=("psnr",))
    events = []
    res = run_bench([scene], elsewhere, tmp_path, on_event=lambda kind, info: events.append((kind, info["method"])))
    assert events[:2] == [("reuse", method_id(methods[0])), ("resume", method_id(methods[1]))]
    assert [r["iterations"] for r in res.rows] == [BASE["iters"]] * 2
    doc = yaml.safe_load((stopped.run / "config.yaml").read_text())
    assert doc["settings"]["threads"] == 2 and doc["settings"]["backend"] == "auto"
    # went on from the checkpoint, not from iteration 0
    assert doc["sources"]["threads"] == f"changed on resume at iteration {done_before}: 2"


def test_pareto_front_on_hand_made_points():
    # (cost, psnr): lower cost and higher PSNR are better
    pts = [(1, 20), (2, 25), (3, 24), (4, 30), (5, 30), (0.5, 10), (2, 25), (None, 40), (6, float("nan"))]
    flags = pareto_front([p[0] for p in pts], [p[1] for p in pts])
    assert flags == [True, True, False, True, False, True, True, False, False]
    assert pareto_front([], []) == []
    assert pareto_front([1.0], [1.0]) == [True]


def test_budget_bytes_from_floats_per_primitive():
    gauss, notes = fit_config_for({"kernel": "gaussian", "budget_bytes": "1MB"}, {"sh_degree": 3})
    learned, lnotes = fit_config_for({"kernel": "learned", "k": 2, "budget_bytes": "1MB"}, {"sh_degree": 3})
    g_bytes, g_nets = bytes_per_primitive(gauss)
    l_bytes, l_nets = bytes_per_primitive(learned)
    assert g_bytes == 4 * (3 + 3 + 4 + 1 + 16 * 3) and g_nets == 0
    assert l_bytes == g_bytes + 4 * 5  # the 5-float latent z3d
    assert l_nets > 0
    assert gauss.train.budget == 2**20 // g_bytes
    assert learned.train.budget == (2**20 - l_nets) // l_bytes
    assert notes["budget"]["bytes_per_primitive"] == g_bytes and lnotes["budget"]["network_bytes"] == l_nets
    assert method_id({"kernel": "learned", "k": 2, "budget_bytes": "1MB"}) == "learned-k2-sh-B1M"
    # a learned method without k runs as fit does without --k (decision 0105), and its id says so
    assert method_id({"kernel": "learned"}) == "learned-kauto-sh"
    assert fit_config_for({"kernel": "learned"})[0].kernel_options["k"] == "auto"


def test_short_runs_scale_schedules():
    cfg, notes = fit_config_for({"kernel": "learned", "k": 4}, {"iters": 3000})
    assert cfg.train.mcmc.refine_start == 50 and cfg.train.mcmc.refine_every == 10 and cfg.train.sh_degree_interval == 100
    assert cfg.kernel_options["freeze_iters"] == 200
    assert cfg.train.scales_lr_mult == round(10**0.5, 3)  # sqrt(30k / 3k)
    assert fit_config_for({}, {"iters": 100})[0].train.scales_lr_mult == 10.0  # capped
    own, _ = fit_config_for({"scales_lr_mult": 2.0}, {"iters": 3000})
    assert own.train.scales_lr_mult == 2.0  # a method's own setting wins
    assert cfg.kernel_options["z3d_lr"] == pytest.approx(1e-3) and cfg.kernel_options["net_lr_mult"] == 10.0
    nopre, _ = fit_config_for({"kernel": "learned", "weights": None}, {"iters": 15000})
    assert nopre.kernel_options["net_lr_mult"] == 10.0  # the no-pretraining x10, not x20
    mine, _ = fit_config_for({"kernel": "learned", "kernel_options": {"z3d_lr": 0.0}}, {"iters": 3000})
    assert mine.kernel_options["z3d_lr"] == 0.0
    full, _ = fit_config_for({"kernel": "learned"}, {"iters": 3000}, scale_schedules=False)
    assert full.train.mcmc.refine_start == 500 and "freeze_iters" not in full.kernel_options
    assert full.train.scales_lr_mult == 1.0
    fit_lrs, _ = fit_config_for({"kernel": "learned", "k": 4}, {"iters": 3000}, scale_lrs=False)
    assert fit_lrs.train.mcmc.refine_every == 10  # schedules still scaled...
    assert fit_lrs.train.scales_lr_mult == 1.0 and "z3d_lr" not in fit_lrs.kernel_options  # ...LRs not
    assert "net_lr_mult" not in fit_lrs.kernel_options


def test_classify_flags_runs_that_end_below_their_start():
    assert classify(12.0, 11.5, 0) == {"below_initial": True, "diverged": True, "nan": False}
    assert classify(12.0, 20.0, 2) == {"below_initial": False, "diverged": False, "nan": True}
    assert classify(12.0, float("nan"), 1)["diverged"]
    assert classify(None, 20.0, 0)["diverged"] is False


def test_stability_matrix_2x2(scene, tmp_path):
    kernels = {"gaussian": {"kernel": "gaussian"}, "learned-k2": {"kernel": "learned", "k": 2}}
    # the demo scene has no SfM points, so the sfm-init column is "not applicable";
    # lr x 1e5 makes the trainer roll back NaNs and the run end below its start: with the
    # collapse checks off (divergence_factor 0) and without the short-run LR boost, which
    # otherwise rescue it here
    conditions = {"sfm-init": {"init": "sfm"}, "lr-x1e5": {"lr_scale": 1e5, "divergence_factor": 0.0}}
    # starting at the budget (not a quarter of it) gives a start that lr x 1e5 must fall below
    cfg = BenchConfig(defaults={**BASE, "iters": 30, "random_points": 200}, metrics=("psnr",),
                      scale_lrs=False)
    res = run_stability([scene], cfg, tmp_path, kernels=kernels, conditions=conditions)
    matrix = json.loads((tmp_path / "stability" / "matrix_demo.json").read_text())
    cells = {(c["row"], c["col"]): c for c in matrix["cells"]}
    assert len(cells) == 4 and len(res.rows) == 4
    assert all(cells[(k, "sfm-init")]["status"] == "not_applicable" for k in kernels)
    for k in kernels:
        c = cells[(k, "lr-x1e5")]
        assert c["status"] == "ok" and math.isfinite(c["psnr"])  # training did not die
        assert c["nan_rollbacks"] >= 1 and c["nan"]
        assert c["below_initial"] and c["diverged"]
        assert c["initial_psnr"] > c["psnr"]
    assert len(list((tmp_path / "stability" / "results").glob("*.json"))) == 4
    img = cv2.imread(str(tmp_path / "charts" / "stability_demo.png"))
    assert img is not None and img.shape[0] > 100
    assert (tmp_path / "charts" / "stability_demo.svg").is_file()


def test_stability_schedules_preset_runs_each_kernel_as_fit_would_at_each_schedule():
    from splatk.bench.methods import load_bench_file
    from splatk.bench.stability import stability_methods
    from splatk_cli.common import find_preset

    st = load_bench_file(find_preset("bench_stability_schedules"))["stability"]
    command_line = {"iters": 1000, "downscale": 4, "budget": 5000}
    cells = stability_methods(command_line, st["kernels"], st["conditions"], scene_has_points=True)
    assert len(cells) == 6 * 3 and all(m is not None and m["init"] == "sfm" for _, _, m, _ in cells)
    for row, col, method, _ in cells:
        cfg, notes = fit_config_for(method)
        got = (cfg.train.iters, cfg.downscale, cfg.sh_degree)
        if col == "short":  # the command line's run, its schedules scaled as fit scales them
            assert got == (1000, 4, 3) and cfg.train.budget == 5000 and "scaled_schedules" in notes
        elif col == "7k":
            assert got == (7000, 2, 3) and cfg.train.budget == 20000 and "scaled_schedules" in notes
        else:  # the paper's equal-memory protocol: 30k unscaled, 1 MB for each kernel
            assert got == (30000, 4, 0) and "scaled_schedules" not in notes
            per_prim, nets = bytes_per_primitive(cfg)
            assert notes["budget"]["budget_bytes"] == 2**20 and cfg.train.budget == (2**20 - nets) // per_prim
        assert cfg.kernel == ("learned" if row.startswith("learned") else row)
        if row == "learned-kauto":
            assert method["k"] == "auto"


# ---- planar primitives ------------------------------------------------------------------------
def test_planar_bytes_per_primitive_counted_from_the_planar_model():
    from splatk.kernels import make_kernel

    gauss, _ = fit_config_for({"kernel": "gaussian", "budget_bytes": "1MB"}, {"sh_degree": 3, "primitive": "planar"})
    learned, notes = fit_config_for({"kernel": "learned", "budget_bytes": "1MB"},
                                    {"sh_degree": 3, "primitive": "planar"})
    g_bytes, g_nets = bytes_per_primitive(gauss)
    l_bytes, l_nets = bytes_per_primitive(learned)
    assert g_bytes == 4 * (3 + 2 + 4 + 1 + 16 * 3) and g_nets == 0  # two in-plane scales
    assert l_bytes == g_bytes + 4 * 10  # the 10-float latent z
    assert l_nets == 4 * sum(p.numel() for p in make_kernel("learned", "planar").parameters()) > 0
    assert gauss.train.budget == 2**20 // g_bytes
    assert learned.train.budget == (2**20 - l_nets) // l_bytes == notes["budget"]["budget"]


def test_planar_method_ids_are_distinct():
    planar = {"primitive": "planar"}
    ids = [method_id({"kernel": "gaussian"}), method_id({"kernel": "gaussian", **planar}),
           method_id({"kernel": "gaussian"}, planar), method_id({"kernel": "learned", "k": 2}),
           method_id({"kernel": "learned", **planar})]
    assert ids == ["gaussian-sh", "planar-gaussian-sh", "planar-gaussian-sh", "learned-k2-sh", "planar-learned-sh"]
    # k is volumetric-only: it neither names nor configures a planar run
    assert method_id({"kernel": "learned", "k": 4, "budget_bytes": "1MB"}, planar) == "planar-learned-sh-B1M"
    cfg, _ = fit_config_for({"kernel": "learned", "k": 4}, {**planar, "iters": 30000})
    assert "k" not in cfg.kernel_options
    # bad settings are input errors, as `splatk fit` reports them
    with pytest.raises(InputError, match="primitive"):
        fit_config_for({"primitive": "voxel"})
    with pytest.raises(InputError, match="no planar version"):  # before any training
        fit_config_for({"kernel": "beta"}, planar)


def test_planar_short_runs_scale_the_planar_kernels_options():
    from splatk.kernels import make_kernel

    cfg, notes = fit_config_for({"kernel": "learned", "primitive": "planar"}, {"iters": 3000})
    assert cfg.kernel_options == {"freeze_iters": 200, "z_lr": pytest.approx(1e-3), "net_lr_mult": 10.0}
    assert notes["scaled_schedules"]["z_lr"] == pytest.approx(1e-3)
    kernel = make_kernel(cfg.kernel, "planar", **cfg.kernel_options)  # every option is the planar kernel's
    assert kernel.learning_rates() == {"z": pytest.approx(1e-3)} and kernel.freeze_iters == 200


def test_tiny_planar_bench(scene, tmp_path):
    cfg = BenchConfig(methods=[{"kernel": "gaussian"}, {"kernel": "learned", "budget_bytes": "64KB"}],
                      defaults={**BASE, "primitive": "planar"}, metrics=("psnr",))
    res = run_bench([scene], cfg, tmp_path, charts=False)
    assert [r["method"] for r in res.rows] == ["planar-gaussian-sh", "planar-learned-sh-B64K"]
    for r in res.rows:
        assert r["status"] == "ok" and math.isfinite(r["psnr"]) and r["config"]["primitive"] == "planar"
    learned = res.rows[1]
    assert learned["num_primitives"] <= learned["derived"]["budget"]["budget"]
    assert learned["footprint_mb"] * 2**20 <= 64 * 2**10


def test_auto_budget_result_keeps_the_whole_report(scene, tmp_path):
    """A `--budget auto` run's result JSON carries the stages as fit.json has them, so the
    report survives deleting the run folders (benchmarks/autobudget.py reads it from there)."""
    cfg = BenchConfig(methods=[{"kernel": "gaussian", "budget": "auto"}],
                      defaults={**BASE, "budget": None, "iters": 60}, metrics=("psnr",))
    (row,) = run_bench([scene], cfg, tmp_path).rows
    fit_report = json.loads((Path(row["run"]) / "fit.json").read_text())["auto_budget"]
    assert row["auto_budget_report"] == fit_report and row["auto_budget"] == fit_report["chosen_budget"]
    assert fit_report["stages"]


@pytest.mark.parametrize("method, defaults, points", [
    ({"kernel": "learned", "k": "auto"}, {}, False),  # config.yaml records the k it chose
    ({"kernel": "gaussian"}, {"init": None}, True),  # ... and init auto as sfm
    ({"kernel": "learned", "k": "auto"}, {"init": None}, True),
    ({"kernel": "gaussian", "budget": "auto"}, {"budget": None, "iters": 60}, False),
    ({"kernel": "gaussian", "strategy": "adc"}, {}, False),
    ({"kernel": "learned", "primitive": "planar"}, {}, False),
], ids=["k-auto", "init-auto-sfm", "k-and-init-auto", "budget-auto", "adc", "planar"])
def test_every_kind_of_stopped_cell_resumes(scene, scene_with_points, tmp_path, method, defaults, points):
    """A cell stopped mid-fit goes on from its checkpoint on the next call, whatever the fit
    derives or records at its start, instead of being started over."""
    scene = scene_with_points if points else scene
    cfg = BenchConfig(methods=[method], defaults={k: v for k, v in {**BASE, **defaults}.items() if v is not None},
                      metrics=("psnr",))
    stopped = _stopped_grid(scene, cfg, tmp_path, polls=10)
    assert (stopped.run / "checkpoints" / "last.pt").is_file()
    events = []
    (row,) = run_bench([scene], cfg, tmp_path, charts=False, on_event=lambda kind, info: events.append(kind)).rows
    assert events == ["resume", "done"] and row["status"] == "ok"


@pytest.mark.parametrize("points", [False, True], ids=["random-init", "init-auto-sfm"])
def test_methods_with_the_same_settings_share_one_run(scene, scene_with_points, tmp_path, monkeypatch, points):
    """`k: auto` on 32 x 32 views at 200 primitives (5 pixels each) chooses k = 2: the grid trains
    that run once and reports it under both ids; k = 8 is a run of its own."""
    methods = [{"kernel": "learned", "k": "auto"}, {"kernel": "learned", "k": 2}, {"kernel": "learned", "k": 8}]
    defaults = {k: v for k, v in BASE.items() if not (points and k == "init")}
    scene = scene_with_points if points else scene
    cfg = BenchConfig(methods=methods, defaults=defaults, metrics=("psnr",))
    calls = _spy_run_fit(monkeypatch)
    events = []
    rows = {r["method"]: r for r in run_bench([scene], cfg, tmp_path, charts=False,
                                             on_event=lambda kind, info: events.append((kind, info))).rows}
    assert calls == [False, False]
    assert [(info["method"], info["as"]) for kind, info in events if kind == "same run"] == [
        ("learned-k2-sh", "learned-kauto-sh")]
    auto, k2, k8 = rows["learned-kauto-sh"], rows["learned-k2-sh"], rows["learned-k8-sh"]
    assert k2["same_run_as"] == "learned-kauto-sh" and k2["run"] == auto["run"]
    assert k2["psnr"] == auto["psnr"] and k2["config"]["kernel_options"]["k"] == 2
    assert "same_run_as" not in k8 and k8["psnr"] != auto["psnr"]
    # a second call reuses all three results
    assert run_bench([scene], cfg, tmp_path, charts=False).rows == list(rows.values()) and calls == [False, False]


def test_a_finished_run_with_the_same_settings_beats_resuming_a_partial_one(scene, tmp_path, monkeypatch):
    k2, auto = {"kernel": "learned", "k": 2}, {"kernel": "learned", "k": "auto"}
    run_bench([scene], BenchConfig(methods=[k2], defaults=BASE, metrics=("psnr",)), tmp_path, charts=False)
    fit_cfg, _ = fit_config_for(auto, BASE)
    run_fit(scene, tmp_path / "runs" / "demo" / method_id(auto), fit_cfg, should_stop=lambda: True)
    calls = _spy_run_fit(monkeypatch)
    events = []
    rows = run_bench([scene], BenchConfig(methods=[auto, k2], defaults=BASE, metrics=("psnr",)), tmp_path,
                     charts=False, on_event=lambda kind, info: events.append(kind)).rows
    assert calls == [] and events[0] == "same run"
    assert {r["method"]: r.get("same_run_as") for r in rows} == {method_id(auto): method_id(k2), method_id(k2): None}
