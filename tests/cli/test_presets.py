"""Every shipped preset loads and resolves to a valid fit configuration."""
from pathlib import Path

import pytest

from splatk.stages.fit_config import fit_config_from_options, parse_duration
from splatk_cli.common import load_preset

PRESETS = sorted((Path(__file__).resolve().parents[2] / "presets").glob("*.yaml"))


@pytest.mark.parametrize("path", PRESETS, ids=[p.stem for p in PRESETS])
def test_preset_loads(path):
    data, found = load_preset(str(path))
    assert isinstance(data, dict) and data and found == path
    if {"defaults", "methods", "grid", "stability"} & set(data):  # a `splatk bench` preset
        from splatk.bench import expand_grid, fit_config_for, load_bench_file

        bench = load_bench_file(path)
        methods = list(bench.get("methods") or []) + expand_grid(bench.get("grid") or {})
        for kernel in (bench.get("stability") or {}).get("kernels", {}).values():
            methods.append(kernel)
        assert methods
        for method in methods:
            fit_config_for(method, bench.get("defaults"))
        return
    cfg, _ = fit_config_from_options({k: v for k, v in data.items() if k not in ("scale_schedules", "short_run_lrs")})
    assert cfg.kernel in ("gaussian", "beta", "student_t", "learned")
    if "budget" in data:
        assert cfg.train.budget == int(data["budget"])
    if "time_budget" in data:
        assert cfg.train.time_budget == parse_duration(data["time_budget"]) > 0


def test_presets_exist():
    names = {p.stem for p in PRESETS}
    assert {"default", "fast", "demo"} <= names


@pytest.mark.parametrize("text,seconds", [("10m", 600), ("90s", 90), ("1h30m", 5400), ("600", 600), ("2.5m", 150)])
def test_parse_duration(text, seconds):
    assert parse_duration(text) == seconds


def test_parse_duration_rejects_garbage():
    with pytest.raises(ValueError):
        parse_duration("ten minutes")


def test_fit_scales_schedules_to_short_runs(tmp_path):
    """`splatk fit --iters N` (N < 30k) shrinks the 30k step schedules in proportion, raises
    the LRs tuned for 30k and says so in config.yaml; --no-scale-schedules keeps both,
    --no-short-run-lrs (or the demo preset) keeps the LRs; 30k runs and timed runs are untouched."""
    import yaml
    from click.testing import CliRunner
    from splatk.data.synthetic import make_demo_scene
    from splatk.stages.fit import FitConfig
    from splatk.stages.run_length import scale_schedules_to_run
    from splatk_cli.main import cli

    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    base = ["fit", str(scene), "--iters", "300", "--budget", "200", "--threads", "1", "-q"]
    res = CliRunner().invoke(cli, base + ["--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    doc = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    train = doc["settings"]["train"]
    assert (train["mcmc"]["refine_every"], train["mcmc"]["refine_start"], train["sh_degree_interval"]) == (5, 5, 10)
    assert "scaled to the run length" in doc["sources"]["refine_every"]
    assert train["mcmc"]["noise_lr"] == 5e5  # MCMC noise x 30k/300, capped at x10
    res = CliRunner().invoke(cli, base + ["--no-scale-schedules", "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    train = yaml.safe_load((tmp_path / "b" / "config.yaml").read_text())["settings"]["train"]
    assert (train["mcmc"]["refine_every"], train["mcmc"]["refine_start"], train["sh_degree_interval"]) == (100, 500, 1000)
    assert train["mcmc"]["noise_lr"] == 5e4

    assert train["scales_lr_mult"] == 1.0  # the 30k run's LRs too
    res = CliRunner().invoke(cli, base + ["--kernel", "learned", "--out", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    doc = yaml.safe_load((tmp_path / "c" / "config.yaml").read_text())
    # 300 of 30k iterations: log-scale LR x sqrt(100) = 10, latent and network LRs x 10 (capped)
    assert doc["settings"]["train"]["scales_lr_mult"] == 10.0
    assert doc["settings"]["kernel_options"]["net_lr_mult"] == 10.0
    assert abs(doc["settings"]["kernel_options"]["z3d_lr"] - 1e-3) < 1e-12
    assert doc["settings"]["kernel_options"]["freeze_iters"] == 20
    assert "scaled to the run length" in doc["sources"]["scales_lr_mult"]
    train_a = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())["settings"]["train"]
    assert train_a["scales_lr_mult"] == 10.0  # the Gaussian's too
    res = CliRunner().invoke(cli, base + ["--no-short-run-lrs", "--out", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    train_d = yaml.safe_load((tmp_path / "d" / "config.yaml").read_text())["settings"]["train"]
    assert train_d["scales_lr_mult"] == 1.0 and train_d["mcmc"]["refine_every"] == 5  # schedules still scaled
    res = CliRunner().invoke(cli, base + ["--preset", "demo", "--out", str(tmp_path / "e")])
    assert res.exit_code == 0, res.output
    train_e = yaml.safe_load((tmp_path / "e" / "config.yaml").read_text())["settings"]["train"]
    assert train_e["scales_lr_mult"] == 1.0  # the demo preset turns the boost off

    full = FitConfig()
    assert scale_schedules_to_run(full) == {} and full.train.mcmc.refine_every == 100
    timed = FitConfig(kernel="learned")
    timed.train.iters, timed.train.time_budget = 1000, 60.0
    assert scale_schedules_to_run(timed) == {} and "freeze_iters" not in timed.kernel_options
    learned = FitConfig(kernel="learned")
    learned.train.iters = 3000
    assert scale_schedules_to_run(learned)["freeze_iters"] == 200
    two_thirds = FitConfig()
    two_thirds.train.iters = 20_000
    scale_schedules_to_run(two_thirds)
    assert scale_schedules_to_run(two_thirds)["noise_lr"] == pytest.approx(5e4 * 1.5)  # scaling twice: same
    kept = FitConfig()
    kept.train.iters, kept.train.mcmc.noise_lr = 2000, 7e3
    assert "noise_lr" not in scale_schedules_to_run(kept, keep={"noise_lr"}) and kept.train.mcmc.noise_lr == 7e3


def test_python_run_fit_trains_as_the_command_does(tmp_path):
    """The short-run scaling belongs to the fit's settings, not to the command line: a Python
    caller that builds its config from the same options writes the same config.yaml settings as
    `splatk fit` (schedules, MCMC noise, the learned kernel's freeze and LRs, the two switches)."""
    import yaml
    from click.testing import CliRunner
    from splatk.data.synthetic import make_demo_scene
    from splatk.stages.fit import run_fit
    from splatk.stages.fit_config import fit_config_from_options
    from splatk_cli.main import cli

    scene = make_demo_scene(tmp_path / "scene", num_views=6, size=24)
    options = {"kernel": "learned", "iters": 30, "budget": 100, "threads": 1, "backend": "torch"}
    flags = [x for k, v in options.items() for x in (f"--{k.replace('_', '-')}", str(v))]
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(tmp_path / "cli"), *flags, "-q"])
    assert res.exit_code == 0, res.output
    cfg, notes = fit_config_from_options(options)
    result = run_fit(scene, tmp_path / "py", cfg)
    by_cli = yaml.safe_load((tmp_path / "cli" / "config.yaml").read_text())
    by_python = yaml.safe_load((result.path / "config.yaml").read_text())
    assert by_python["settings"] == by_cli["settings"]
    settings = by_python["settings"]
    assert settings["scale_schedules"] and settings["short_run_lrs"]
    assert settings["train"]["mcmc"]["refine_every"] == 5 and settings["kernel_options"]["freeze_iters"] == 2
    assert notes["scaled_schedules"]["net_lr_mult"] == settings["kernel_options"]["net_lr_mult"] == 10.0
    assert result.summary["iterations"] == 30 and result.summary["kernel"] == "learned"


def test_config_files_of_older_runs_still_load():
    """A run folder written before MCMC's settings moved under train.mcmc (and before the
    run-length switches were settings) still loads for --resume, and goes on without
    relocate_one_view, which it trained without."""
    from splatk.stages.autobudget import AutoBudgetConfig
    from splatk.stages.fit_config import FitConfig

    old = FitConfig().to_dict()
    mcmc = old["train"].pop("mcmc")
    old["train"].update({k: mcmc[k] for k in ("refine_every", "refine_start", "refine_stop", "noise_lr",
                                              "split_scales", "hold_growth")})
    old["train"]["refine_every"] = 7
    del old["scale_schedules"], old["short_run_lrs"]
    old["auto_budget"] = {"selection": "short_runs", "paired": True, "refit": True, "return_holdout": True}
    cfg = FitConfig.from_dict(old)
    assert cfg.train.mcmc.refine_every == 7 and cfg.train.mcmc.noise_lr == 5e4
    assert FitConfig().train.mcmc.relocate_one_view and not cfg.train.mcmc.relocate_one_view
    assert cfg.auto_budget == AutoBudgetConfig() and cfg.scale_schedules
