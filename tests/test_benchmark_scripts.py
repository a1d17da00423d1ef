"""Every benchmark script still imports what it uses from splatk: a rename in the engine that a
script was not updated for fails here rather than when someone reruns the benchmark."""
from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest
import torch

from splatk import backends, metrics
from splatk.functional.projection import quats_to_rotmats
from tests.scenes import orbit_cameras, random_model

SCRIPTS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))


def load_script(script: Path):
    """The benchmark script as a module: its imports and definitions run, not main()."""
    spec = importlib.util.spec_from_file_location(f"benchmark_{script.stem}", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_benchmark_script_imports(script):
    module = load_script(script)
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"


@torch.no_grad()
def test_learned_view_dependence_hooks():
    """The cap never binds in a view it was recorded in, the view average of one view is that view,
    another view is changed by both, and the model renders as fitted once the hook is gone."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_view_dependence"))
    model = random_model(40, seed=3, kernel="learned")
    model.prims["z3d"].data[:] = 2.0 * torch.randn(40, model.kernel.latent_dim,
                                                   generator=torch.Generator().manual_seed(0))
    seen, other = orbit_cameras(4, size=32)[0], orbit_cameras(4, size=32)[2]
    backend = backends.get("torch")
    bg = torch.zeros(3)

    def image(cam):
        return model.render(cam, bg, backend=backend).image

    fitted_seen, fitted_other = image(seen), image(other)
    train = script.TrainViewProfiles(model.num_primitives, model.kernel.k)
    with script.profile_hook(model, train.record):
        assert torch.equal(image(seen), fitted_seen)
    for hook in (train.capped, train.view_averaged):
        with script.profile_hook(model, hook):
            assert torch.allclose(image(seen), fitted_seen, atol=1e-6)
            assert not torch.allclose(image(other), fitted_other, atol=1e-4)
    assert script.INDEX_KEY not in model.prims
    assert torch.equal(image(other), fitted_other)


def test_learned_view_dependence_turns_by_the_angle_asked():
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_view_dependence"))
    turns = script.random_rotations(100, 10.0, torch.Generator().manual_seed(0))
    assert torch.allclose(turns @ turns.transpose(1, 2), torch.eye(3).expand(100, 3, 3), atol=1e-6)
    cos_angle = (turns.diagonal(dim1=1, dim2=2).sum(1) - 1.0) / 2.0  # trace = 1 + 2 cos(angle)
    assert torch.allclose(cos_angle, torch.full((100,), math.cos(math.radians(10.0))), atol=1e-6)


def test_learned_validation_makes_each_scene_once_before_parallel_cells(tmp_path, monkeypatch):
    """Two cells of one made scene run in parallel; each making the scene would have two
    processes write the same folder at once."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    made = []

    def fake_run(cmd, **kwargs):
        if str(cmd[1]).endswith("make_frontal_scene.py"):
            made.append(cmd[3])
            Path(cmd[3]).mkdir(parents=True)

    fitted = []
    monkeypatch.setattr(script.subprocess, "run", fake_run)
    monkeypatch.setattr(script, "run_one", lambda scene, kernel, *a, **k: fitted.append((scene, kernel)))
    monkeypatch.setattr("sys.argv", ["learned_validation.py", str(tmp_path), "--scenes", "juicebox_arc2",
                                     "--kernels", "gaussian,learned", "--jobs", "2"])
    script.main()
    assert made == [str(tmp_path / "scenes" / "juicebox_arc2")]
    assert sorted(fitted) == [("juicebox_arc2", "gaussian"), ("juicebox_arc2", "learned")]


def test_learned_validation_pretrains_a_candidates_networks_once_and_fits_with_them(tmp_path, monkeypatch):
    """learned-z1's cells fit with networks pretrained for a 1-float latent, made once for the grid
    (two parallel cells each pretraining would write one file twice); the default learned cell
    fits with the shipped networks."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append([str(c) for c in cmd])
        if cmd[:2] == ["splatk", "pretrain"]:
            Path(cmd[3]).write_bytes(b"weights")

    monkeypatch.setattr(script.subprocess, "run", fake_run)
    for _ in range(2):
        assert script.pretrained_weights("learned-z1", tmp_path) == ["--kernel-weights",
                                                                     str(tmp_path / "weights" / "learned-z1.pt")]
    assert script.pretrained_weights("learned", tmp_path) == []
    pretrains = [c for c in calls if c[:2] == ["splatk", "pretrain"]]
    assert len(pretrains) == 1 and pretrains[0][4:6] == ["--latent-dim", "1"]


def _row(scene, kernel, psnr):
    return {"scene": scene, "kernel": kernel, "set": "validation", "test_psnr": psnr, "train_psnr": psnr + 5,
            "primitives": 10, "k": None, "rollbacks": 0}


def test_learned_validation_grid_in_parts_keeps_every_part(tmp_path, monkeypatch):
    """A grid run one scene at a time keeps each scene's rows in the seed's result file."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    monkeypatch.setattr(script, "run_one", lambda scene, kernel, *a, **k: _row(scene, kernel, 20.0))
    for scene in ("kangaroo", "juicebox"):
        monkeypatch.setattr("sys.argv", ["learned_validation.py", str(tmp_path), "--protocol", "30k", "--seed", "1",
                                         "--scenes", scene, "--kernels", "gaussian,learned"])
        script.main()
    rows = json.loads((tmp_path / "learned_validation_30k_seed1.json").read_text())["rows"]
    assert sorted((r["scene"], r["kernel"]) for r in rows) == [
        ("juicebox", "gaussian"), ("juicebox", "learned"), ("kangaroo", "gaussian"), ("kangaroo", "learned")]


def test_learned_validation_over_seeds_reads_saved_rows(tmp_path):
    """Without run folders, --over-seeds pairs the rows the grids saved, seed by seed."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    for seed, (gaussian, learned) in enumerate([(24.0, 25.0), (23.0, 23.5)]):
        rows = [_row("kangaroo", "gaussian", gaussian), _row("kangaroo", "learned", learned)]
        script.result_file(tmp_path, "30k", seed).write_text(json.dumps({"rows": rows}))
    doc = script.over_seeds(tmp_path, "30k", ["kangaroo", "cup"], ["gaussian", "learned"])
    assert doc["seeds_found"] == [0, 1]
    (row,) = doc["per_scene"]
    assert row["seeds"] == [0, 1] and row["set"] == "validation"
    assert row["gaps"] == [1.0, 0.5]
    assert math.isclose(row["gap_mean"], 0.75) and math.isclose(row["gap_standard_error"], 0.25)


def test_learned_validation_over_seeds_charts_every_seed(tmp_path, monkeypatch):
    """--over-seeds draws a line per (scene, kernel) with a dot per seed beside the JSON; a one-seed
    scene (no standard error) is drawn too."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    for seed, (gaussian, learned) in enumerate([(24.0, 25.0), (23.0, 23.5)]):
        rows = [_row("kangaroo", "gaussian", gaussian), _row("kangaroo", "learned", learned)]
        if seed == 0:
            rows += [_row("cup", "gaussian", 30.0), _row("cup", "learned", 30.25)]
        script.result_file(tmp_path, "30k", seed).write_text(json.dumps({"rows": rows}))
    monkeypatch.setattr("sys.argv", ["learned_validation.py", str(tmp_path), "--protocol", "30k", "--over-seeds",
                                     "--scenes", "kangaroo,cup"])
    script.main()
    doc = json.loads((tmp_path / "learned_validation_30k_over_seeds.json").read_text())
    assert [(r["scene"], r["gaps"]) for r in doc["per_scene"]] == [("kangaroo", [1.0, 0.5]), ("cup", [0.25])]
    chart = tmp_path / "learned_validation_30k_over_seeds.png"
    assert chart.stat().st_size > 1000 and chart.with_suffix(".svg").exists()
    assert script.draw_seed_gaps({**doc, "per_scene": []}, tmp_path / "empty") == []


def test_learned_validation_over_seeds_against_another_baseline(tmp_path):
    """--baseline learned-k2 measures a candidate k against k = 2, and the Gaussian is then just another
    kernel: the gaps change sign with the baseline."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    for seed, (gaussian, k2, k4) in enumerate([(24.0, 25.0, 25.5), (23.0, 23.5, 24.5)]):
        rows = [_row("beer_can", "gaussian", gaussian), _row("beer_can", "learned-k2", k2),
                _row("beer_can", "learned-k4", k4)]
        script.result_file(tmp_path, "7k", seed).write_text(json.dumps({"rows": rows}))
    doc = script.over_seeds(tmp_path, "7k", ["beer_can"], ["gaussian", "learned-k2", "learned-k4"],
                            baseline="learned-k2")
    gaps = {r["kernel"]: r["gap_mean"] for r in doc["per_scene"]}
    assert doc["baseline"] == "learned-k2" and set(gaps) == {"gaussian", "learned-k4"}
    assert math.isclose(gaps["learned-k4"], 0.75) and math.isclose(gaps["gaussian"], -0.75)
    (k4,) = [a for a in doc["averages"] if a["kernel"] == "learned-k4"]
    assert k4["scenes_below_baseline"] == 0


@pytest.mark.parametrize("stopped", [True, False], ids=["stopped-part-way", "new"])
def test_learned_validation_resumes_a_cell_that_stopped(tmp_path, monkeypatch, stopped):
    """A cell with a checkpoint and no eval.json goes on with `fit --resume`; `--overwrite`
    (which would throw its iterations away) is for a cell not started."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_validation"))
    run = tmp_path / "runs" / "30k_seed1" / "kangaroo_learned"
    if stopped:
        (run / "checkpoints").mkdir(parents=True)
        (run / "checkpoints" / "last.pt").write_bytes(b"")
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append([str(c) for c in cmd])
        run.mkdir(parents=True, exist_ok=True)
        if cmd[1] == "fit":  # what a finished fit leaves
            (run / "fit.json").write_text(json.dumps({"num_primitives": 10}))
            (run / "train_log.jsonl").write_text(json.dumps({"it": 1, "event": None}) + "\n")
            (run / "config.yaml").write_text("settings: {kernel_options: {k: 2}, device: cpu}\n")
        elif "--split" in cmd:
            (run / "metrics_train.json").write_text(json.dumps({"mean": {"psnr": 30.0}}))
        return type("Done", (), {"stdout": json.dumps({"mean": {"psnr": 25.0}})})()

    monkeypatch.setattr(script.subprocess, "run", fake_run)
    row = script.run_one("kangaroo", "learned", "30k", 1, tmp_path, data=tmp_path)
    fit = next(c for c in calls if c[1] == "fit")
    assert ("--resume" in fit) is stopped
    assert ("--overwrite" in fit) is not stopped
    assert fit[fit.index("--out") + 1] == str(run)
    assert row["test_psnr"] == 25.0 and row["train_psnr"] == 30.0


def test_adc_check_gives_mcmc_the_adc_count_and_resumes_a_stopped_arm(tmp_path, monkeypatch):
    """The MCMC arm's budget is the ADC arm's final count; the regularised ADC arm adds MCMC's
    opacity and scale regularisers to `--strategy adc`, the single-regulariser arms one each; an arm
    with a checkpoint and no eval.json goes on with `fit --resume` and is not refitted from scratch."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "adc_check"))
    stopped = tmp_path / "runs" / "adc-reg"
    (stopped / "checkpoints").mkdir(parents=True)
    (stopped / "checkpoints" / "last.pt").write_bytes(b"")
    counts = {"adc": 1234, "adc-reg": 999, "adc-opacity-reg": 998, "adc-scale-reg": 997, "mcmc": 1000}
    calls = []

    def fake_run(cmd, **kwargs):
        cmd = [str(c) for c in cmd]
        calls.append(cmd)
        run = Path(cmd[cmd.index("--out") + 1] if "--out" in cmd else cmd[2])
        run.mkdir(parents=True, exist_ok=True)
        if cmd[1] == "fit":
            (run / "fit.json").write_text(json.dumps({"num_primitives": counts[run.name], "events": []}))
            (run / "train_log.jsonl").write_text(json.dumps({"it": 1000, "num": counts[run.name]}) + "\n")
        elif "--split" in cmd:
            (run / "metrics_train.json").write_text(json.dumps({"mean": {"psnr": 40.0}}))
        return type("Done", (), {"stdout": json.dumps({"mean": {"psnr": 30.0, "ssim": 0.9}})})()

    monkeypatch.setattr(script.subprocess, "run", fake_run)
    monkeypatch.setattr(script.platform, "processor", lambda: "cpu")  # it would run `uname -p`
    monkeypatch.setattr("sys.argv", ["adc_check.py", str(tmp_path), "--scene", str(tmp_path),
                                     "--arms", "adc,adc-reg,adc-scale-reg,mcmc", "--iters", "50"])
    script.main()
    fits = {Path(c[c.index("--out") + 1]).name: c for c in calls if c[1] == "fit"}
    assert fits["mcmc"][fits["mcmc"].index("--budget") + 1] == "1234"
    assert "--resume" in fits["adc-reg"] and "--overwrite" not in fits["adc-reg"]
    assert "--overwrite" in fits["adc"] and "--opacity-reg" not in fits["adc"]
    reg = script.ARM_FLAGS["adc-reg"]
    assert reg[:2] == ["--strategy", "adc"]
    assert reg[reg.index("--opacity-reg") + 1] == "0.01" and reg[reg.index("--scale-reg") + 1] == "0.01"
    assert "--scale-reg" in fits["adc-scale-reg"] and "--opacity-reg" not in fits["adc-scale-reg"]
    assert "adc-opacity-reg" not in fits  # only the arms asked for run
    assert "--opacity-reg" in script.ARM_FLAGS["adc-opacity-reg"]
    assert "--scale-reg" not in script.ARM_FLAGS["adc-opacity-reg"]
    written = json.loads((tmp_path / "adc_check.json").read_text())
    assert written["results"]["3dgs-mcmc"]["train_psnr"] == 40.0
    assert written["adc-reg"]["final_primitives"] == 999
    assert written["adc-scale-reg"]["final_primitives"] == 997 and written["adc-opacity-reg"] is None


def test_turn_penalty_joins_the_loss_of_training_renders_only():
    """With the penalty installed, the trainer's regularisers after a render with gradients carry
    the turn change (positive for a turn, zero for none), whose gradient reaches the latents and not
    the centres; a render without gradients adds nothing, and leaving the block restores training."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_turn_penalty"))
    import splatk.train.trainer as trainer_module

    plain_regularisers = trainer_module.regularisers
    model = random_model(40, seed=3, kernel="learned")
    model.prims["z3d"].data[:] = 2.0 * torch.randn(40, model.kernel.latent_dim,
                                                   generator=torch.Generator().manual_seed(0))
    cam, backend, bg = orbit_cameras(4, size=32)[0], backends.get("torch"), torch.zeros(3)
    for degrees, turned in ((10.0, True), (0.0, False)):
        with script.TurnPenalty(1.0, degrees).installed():
            with torch.no_grad():
                model.render(cam, bg, backend=backend)
            assert float(trainer_module.regularisers(model, 0.0, 0.0)) == 0.0
            model.render(cam, bg, backend=backend)
            penalty = trainer_module.regularisers(model, 0.0, 0.0)
            assert (float(penalty.detach()) > 1e-8) is turned, float(penalty.detach())
            if turned:
                penalty.backward()
                assert model.prims["z3d"].grad.abs().sum() > 0
                assert model.prims["means"].grad is None or not model.prims["means"].grad.any()
    assert trainer_module.regularisers is plain_regularisers


def test_turn_penalty_by_the_train_view_gap_turns_by_it_and_is_off_under_its_floor():
    """Cameras 30 degrees apart on a ring looking at its centre have a train-view gap of 30 degrees
    (an uneven ring: the median); ``--degrees gap`` turns by it, and where the gap is under
    ``--from-gap`` the penalty adds nothing to training."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_turn_penalty"))
    import splatk.train.trainer as trainer_module
    from splatk.data.types import Camera
    from tests.scenes import look_at

    def ring(azimuths_deg):
        return [Camera(f"v{i}.png", 32, 32, 30.0, 30.0, 16.0, 16.0,
                       look_at((4 * math.cos(math.radians(a)), 4 * math.sin(math.radians(a)), 0.0)))
                for i, a in enumerate(azimuths_deg)]

    assert math.isclose(script.train_view_gap(ring(range(0, 360, 30))), 30.0, abs_tol=1e-3)
    # azimuths 0, 10, 20 and 40: each camera's nearest is 10, 10, 10 and 20 degrees away
    assert math.isclose(script.train_view_gap(ring([0, 10, 20, 40])), 10.0, abs_tol=1e-3)
    assert script.train_view_gap(ring([0])) == 0.0

    scene = type("Scene", (), {"train": ring(range(0, 360, 30))})()
    model = random_model(40, seed=3, kernel="learned")
    model.prims["z3d"].data[:] = 2.0 * torch.randn(40, model.kernel.latent_dim,
                                                   generator=torch.Generator().manual_seed(0))
    cam, backend, bg = orbit_cameras(4, size=32)[0], backends.get("torch"), torch.zeros(3)
    for from_gap, on in ((20.0, True), (40.0, False)):
        penalty = script.TurnPenalty(1.0, script.GAP, from_gap=from_gap)
        penalty.set_scene(scene)
        assert math.isclose(penalty.degrees, 30.0, abs_tol=1e-3) and (penalty.weight == 1.0) is on
        with penalty.installed():
            model.render(cam, bg, backend=backend)
            added = float(trainer_module.regularisers(model, 0.0, 0.0).detach())
        assert (added > 1e-8) is on, added


def test_kernel_table_measures_learned_against_the_best_analytic_kernel(tmp_path, monkeypatch, capsys):
    """3DGS-ADC and `--k auto` get their own rows; Tab. 2's count takes the best analytic kernel
    of a scene (here ADC on one scene, Beta on the other) and only scenes where all four ran."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "kernel_table"))
    results = tmp_path / "results"
    results.mkdir()
    grid = {"a": {"3dgs-adc": 25.0, "gaussian": 24.0, "beta": 24.5, "student_t": 24.2, "learned-k2": 25.4,
                  "learned-k8": 25.8, "learned-auto": 25.6},
            "b": {"3dgs-adc": 20.0, "gaussian": 21.0, "beta": 22.0, "student_t": 21.5, "learned-k2": 22.1,
                  "learned-auto": 22.6},
            "c": {"gaussian": 20.0, "learned-k2": 23.0}}
    # each row's method as `splatk bench` records it
    specs = {"3dgs-adc": {"kernel": "gaussian", "strategy": "adc"}, "gaussian": {"kernel": "gaussian"},
             "beta": {"kernel": "beta"}, "student_t": {"kernel": "student_t"},
             "learned-k2": {"kernel": "learned", "k": 2}, "learned-k8": {"kernel": "learned", "k": 8},
             "learned-auto": {"kernel": "learned", "k": "auto"}}
    for scene, cells in grid.items():
        for name, value in cells.items():
            row = {"status": "ok", "scene": scene, "psnr": value, "ssim": 0.9, "num_primitives": 100,
                   "method_spec": {**specs[name], "budget_bytes": "1MB"},
                   "loss_rollbacks": 1 if name == "3dgs-adc" else 0,
                   "config": {"kernel_options": {"k": 4}}}
            (results / f"{scene}__{name}.json").write_text(json.dumps(row))
    out = tmp_path / "table.json"
    monkeypatch.setattr("sys.argv", ["kernel_table.py", str(tmp_path), "--json", str(out)])
    script.main()
    printed = capsys.readouterr().out
    assert "| 3dgs-adc | 25.00 / 0.900 (100, 1 rollback) | 20.00" in printed
    assert "(100, k = 4)" in printed
    summary = json.loads(out.read_text())["budgets"]["1MB"]
    a, b = summary["scenes"]["a"], summary["scenes"]["b"]
    assert a["best_analytic"] == "3dgs-adc" and math.isclose(a["best_minus_best_analytic"], 0.8)
    assert math.isclose(a["auto_minus_best_analytic"], 0.6)
    assert b["best_analytic"] == "beta" and math.isclose(b["best_minus_best_analytic"], 0.1)
    assert summary["scenes_with_every_analytic"] == 2  # c has the Gaussian only
    assert summary["met_tab2_best_k"] == 1 and summary["met_tab2_auto"] == 2  # b: auto +0.6, k = 2 +0.1
    assert summary["met_best_k"] == 3  # learned vs the Gaussian alone counts c too


def test_kernel_table_draws_a_line_per_kernel_through_its_budgets(tmp_path, monkeypatch):
    script = load_script(next(s for s in SCRIPTS if s.stem == "kernel_table"))
    results = tmp_path / "results"
    results.mkdir()
    for budget, mb in (("256KB", 0.25), ("512KB", 0.5)):
        for spec, psnr in (({"kernel": "gaussian"}, 24.0 + mb), ({"kernel": "learned", "k": 4}, 23.0 + 4 * mb)):
            row = {"status": "ok", "scene": "a", "psnr": psnr, "ssim": 0.9, "num_primitives": 100,
                   "footprint_mb": mb, "render_ms": 10 * mb, "method_spec": {**spec, "budget_bytes": budget}}
            (results / f"a__{spec['kernel']}-{budget}.json").write_text(json.dumps(row))
    monkeypatch.setattr("sys.argv", ["kernel_table.py", str(tmp_path)])
    script.main()
    import cv2

    for stem in ("kernels_psnr_vs_mb", "kernels_psnr_vs_render_ms"):
        image = cv2.imread(str(tmp_path / "charts" / f"{stem}.png"))
        assert image is not None and image.shape[1] > 200
    cells = {("256KB", "a"): {"gaussian": {"psnr": 24.25, "footprint_mb": 0.25}},
             ("512KB", "a"): {"gaussian": {"psnr": 24.5, "footprint_mb": 0.5},
                              "learned-k4": {"psnr": 25.0, "footprint_mb": float("nan")}}}
    assert script.kernel_series(cells, "footprint_mb") == {"a": {"gaussian": [(0.25, 24.25), (0.5, 24.5)]}}


def learned_model_and_views():
    """A learned model with latents far from zero (so that the view changes its profiles), five
    train cameras around it and a sixth, new one; the torch backend, a black background."""
    model = random_model(40, seed=3, kernel="learned")
    model.prims["z3d"].data[:] = 2.0 * torch.randn(40, model.kernel.latent_dim,
                                                   generator=torch.Generator().manual_seed(0))
    cams = orbit_cameras(6, size=32)
    return model, cams[:5], cams[5], backends.get("torch"), torch.zeros(3)


@torch.no_grad()
def test_learned_donor_view_swaps_profiles_only_where_the_view_is_new():
    """A view that is itself a train view is every primitive's donor, so it renders as fitted;
    a new view draws other profiles; each primitive's donor is the train view, among those that
    see it, whose direction to it is nearest the new view's."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_donor_view"))
    model, train, new, backend, bg = learned_model_and_views()

    def fitted(cam):
        return model.render(cam, bg, backend=backend).image.clamp(0, 1)

    swapped, angle = script.render_with_train_profiles(model, backend, train, train[2], bg)
    assert fitted(train[2]).amax() > 0.2  # the primitives are in view
    assert torch.allclose(swapped, fitted(train[2]), atol=1e-6) and angle < 0.05  # float32 acos near 1
    swapped, angle = script.render_with_train_profiles(model, backend, train, new, bg)
    assert not torch.allclose(swapped, fitted(new), atol=1e-3) and angle > 1.0
    assert torch.equal(fitted(new), model.render(new, bg, backend=backend).image.clamp(0, 1))

    donor, _ = script.donors(model, backend, train, new)
    means = model.prims["means"]
    to_new = torch.nn.functional.normalize(means - script.camera_pose(new)[0], dim=1)
    for i in range(len(means)):
        seen_by = [t for t, cam in enumerate(train) if script.visible_in(model, backend, cam)[i]]
        if not seen_by:
            assert donor[i] == -1
            continue
        cosines = [float(torch.nn.functional.normalize(means[i] - script.camera_pose(train[t])[0], dim=0) @ to_new[i])
                   for t in seen_by]
        assert donor[i] == seen_by[max(range(len(seen_by)), key=cosines.__getitem__)]


@torch.no_grad()
def test_learned_held_inputs_hold_only_what_the_train_views_did_not_show():
    """A train view draws as fitted under every variant; in a new view each primitive seen by a
    train camera gets a distance inside its train distances and is turned so that the camera sees
    it from at most the allowed angle off the nearest train direction, and no further than that."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_held_inputs"))
    model, train, new, backend, bg = learned_model_and_views()
    centres, sees = script.train_sight(model, backend, train)

    fitted = model.render(train[2], bg, backend=backend).image.clamp(0, 1)
    assert fitted.amax() > 0.2  # the primitives are in view
    for clamp_distance, max_turn_deg in script.VARIANTS.values():
        held = script.render_held(model, backend, train[2], bg, centres, sees, clamp_distance, max_turn_deg)
        assert torch.allclose(held, fitted, atol=5e-4)  # float32 acos near 1: a turn of ~0.03 degrees at most
    held = script.render_held(model, backend, new, bg, centres, sees, True, 0.0)
    assert not torch.allclose(held, model.render(new, bg, backend=backend).image.clamp(0, 1), atol=1e-3)

    means, quats = model.prims["means"], model.prims["quats"]
    world_to_cam = new.world_to_cam
    rot = world_to_cam[:3, :3]
    means_cam = means @ rot.T + world_to_cam[:3, 3]
    rotmats_cam = rot @ quats_to_rotmats(quats)
    to_view = torch.nn.functional.normalize(means - script.camera_pose(new)[0], dim=1)
    for max_turn in (0.0, 10.0):
        turned = 0
        held_means, held_rot = script.held_inputs(means, means_cam, rotmats_cam, new, centres, sees,
                                                  True, max_turn)
        for i in range(len(means)):
            seen_by = torch.nonzero(sees[i]).flatten()
            if len(seen_by) == 0:
                assert torch.allclose(held_means[i], means_cam[i]) and torch.allclose(held_rot[i], rotmats_cam[i])
                continue
            dist = (means[i] - centres[seen_by]).norm(dim=1)
            assert dist.min() - 1e-5 <= held_means[i].norm() <= dist.max() + 1e-5
            # the direction the held inputs show: this camera's direction in the primitive's turned frame,
            # taken back to the world by the primitive's own rotation
            shown = rot.T @ rotmats_cam[i] @ held_rot[i].T @ rot @ to_view[i]
            directions = torch.nn.functional.normalize(means[i] - centres[seen_by], dim=1)
            off = math.degrees(math.acos(min(1.0, float((directions @ shown).max()))))
            before = math.degrees(math.acos(min(1.0, float((directions @ to_view[i]).max()))))
            assert off == pytest.approx(min(before, max_turn), abs=0.2)  # float32 acos near 1
            turned += before > max_turn + 5
        assert turned > 5  # the new view is far enough out that the turn binds


@torch.no_grad()
def test_learned_view_support_weighs_and_leaves_out_what_it_is_asked():
    """No primitive carries no blending weight and changes no view; all carry all of it, and the
    view drawn without them is the background."""
    script = load_script(next(s for s in SCRIPTS if s.stem == "learned_view_support"))
    model, _, new, backend, bg = learned_model_and_views()
    none = torch.zeros(model.num_primitives, dtype=torch.bool)
    some = torch.arange(model.num_primitives) % 2 == 0
    fitted = model.render(new, bg, backend=backend).image.clamp(0, 1)
    assert fitted.amax() > 0.2  # the primitives are in view
    new.image = torch.randint(0, 256, fitted.shape, generator=torch.Generator().manual_seed(1), dtype=torch.uint8)
    assert script.blending_weight_share(model, backend, new, none) == 0.0
    assert script.blending_weight_share(model, backend, new, ~none) == pytest.approx(1.0)
    assert 0.05 < script.blending_weight_share(model, backend, new, some) < 0.95
    assert script.psnr_without(model, backend, new, bg, none) == pytest.approx(float(metrics.psnr(fitted, new.image_float())))
    blank = bg.expand_as(fitted)
    assert script.psnr_without(model, backend, new, bg, ~none) == pytest.approx(float(metrics.psnr(blank, new.image_float())), abs=1e-3)
    assert torch.equal(model.render(new, bg, backend=backend).image.clamp(0, 1), fitted)  # opacities restored


def test_train_view_hold_measures_a_run_both_ways_and_leaves_it_as_it_was(tmp_path):
    """A learned run measured without and with its train cameras: its train views read the same (the
    hold never binds there) and the run folder is not written to."""
    from splatk.data.synthetic import make_demo_scene
    from splatk.stages.fit import FitConfig, run_fit
    from splatk.train.trainer import TrainConfig

    script = load_script(next(s for s in SCRIPTS if s.stem == "train_view_hold"))
    scene = make_demo_scene(tmp_path / "scene", num_views=8, size=24)
    cfg = FitConfig(kernel="learned", sh_degree=1, backend="torch", threads=1,
                    train=TrainConfig(iters=5, budget=100, init="random", backend="torch"))
    run = run_fit(scene, tmp_path / "run", cfg).path
    files = sorted(p.name for p in run.iterdir())
    row = script.measure(run, "train")
    assert len(row["views"]) > 0 and abs(row["change"]) < 1e-4
    # fit now keeps the cameras: the "fitted" copy leaves them out, the held one keeps the scene's
    from splatk.models.io import load_model
    assert load_model(run / "model.pt")[0].train_views is not None
    assert load_model(script.model_copy(run, tmp_path / "without", False) / "model.pt")[0].train_views is None
    held = load_model(script.model_copy(run, tmp_path / "with", True) / "model.pt")[0]
    assert len(held.train_views) == len(row["views"])
    assert all(abs(v["held"] - v["fitted"]) < 1e-4 for v in row["views"])
    assert sorted(p.name for p in run.iterdir()) == files
