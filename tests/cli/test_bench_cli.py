"""`splatk bench` on the command line: runs, results, table, resume, stability, method flags."""
from __future__ import annotations

import json

import click
import cv2
import pytest
import torch
from click.testing import CliRunner

from splatk.data.synthetic import make_demo_scene
from splatk_cli.bench import check_grid_flags, build_methods
from splatk_cli.main import cli


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("bench_cli") / "demo", num_views=8, size=32)


def _bench(*args):
    res = CliRunner().invoke(cli, ["bench", *map(str, args)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res


def test_bench_flags_run_resume_and_chart(scene, tmp_path):
    args = (scene, "--out", tmp_path, "--preset", "bench_quick", "--kernel", "gaussian", "--budget", "150",
            "--iters", "30", "--threads", "1")
    res = _bench(*args)
    result = json.loads((tmp_path / "results" / "demo__gaussian-sh-b150.json").read_text())
    assert result["status"] == "ok" and result["num_primitives"] <= 150 and result["threads"] == 1
    assert result["config"]["train"]["iters"] == 30  # the flag beat the preset's 60
    assert "gaussian-sh-b150" in res.stdout and "threads per run: 1" in res.stdout and "fit" in res.stderr
    assert cv2.imread(str(tmp_path / "charts" / "psnr_vs_train_seconds.png")) is not None
    again = _bench(*args)
    assert "reuse" in again.stderr and "      fit" not in again.stderr


def test_bench_primitive_flag_runs_planar(scene, tmp_path):
    res = _bench(scene, "--out", tmp_path, "--kernel", "gaussian", "--budget", "100", "--primitive", "planar",
                 "--iters", "10", "--threads", "1", "--metrics", "psnr")
    result = json.loads((tmp_path / "results" / "demo__planar-gaussian-sh-b100.json").read_text())
    assert result["status"] == "ok" and result["config"]["primitive"] == "planar"
    assert "demo / planar-gaussian-sh-b100" in res.stderr  # (the table may fold long ids)


def test_bench_stability_cli(scene, tmp_path):
    res = _bench(scene, "--out", tmp_path, "--preset", "bench_quick", "--stability", "--iters", "20")
    matrix = json.loads((tmp_path / "stability" / "matrix_demo.json").read_text())
    assert {(c["row"], c["col"]) for c in matrix["cells"]} == {
        ("gaussian", "random-init"), ("gaussian", "lr-x10"), ("learned-k2", "random-init"), ("learned-k2", "lr-x10")}
    assert all(c["status"] == "ok" and c["initial_psnr"] is not None for c in matrix["cells"])
    assert (tmp_path / "charts" / "stability_demo.png").is_file()
    assert "lr-x10" in res.stdout


def test_bench_device_reaches_fit_and_eval(scene, tmp_path):
    """--device goes into every run's settings; a device this machine lacks stops the bench
    before any run, with one line, instead of failing every run."""
    _bench(scene, "--out", tmp_path, "--kernel", "gaussian", "--budget", "100", "--iters", "10",
           "--threads", "1", "--metrics", "psnr", "--device", "cpu")
    result = json.loads((tmp_path / "results" / "demo__gaussian-sh-b100.json").read_text())
    assert result["status"] == "ok" and result["config"]["device"] == "cpu"
    missing = "cuda:99" if torch.cuda.is_available() else "cuda"
    res = CliRunner().invoke(cli, ["bench", str(scene), "--out", str(tmp_path / "b2"), "--kernel", "gaussian",
                                   "--iters", "10", "--device", missing])
    assert res.exit_code != 0 and "--device" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "b2" / "results").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_bench_stability_on_cuda(scene, tmp_path):
    """`bench --device cuda` fits and evaluates every cell on the GPU with the cuda backend."""
    _bench(scene, "--out", tmp_path, "--preset", "bench_quick", "--stability", "--iters", "60",
           "--device", "cuda", "--metrics", "psnr")
    for path in (tmp_path / "results").glob("*.json"):
        row = json.loads(path.read_text())
        assert row["status"] == "ok" and row["config"]["device"] == "cuda" and row["backend"] == "cuda", row
        assert row["psnr"] == row["psnr"] and row["iterations"] == 60, (path.name, row["psnr"])


def test_method_flags_make_a_grid():
    ms = build_methods(("gaussian", "learned"), (2, 8), "none", ("sh",), (), ("1MB", "4MB"))
    assert len(ms) == 6
    assert {"kernel": "learned", "k": 8, "weights": "none", "color": "sh", "budget_bytes": "4MB"} in ms
    assert {"kernel": "gaussian", "color": "sh", "budget_bytes": "1MB"} in ms


@pytest.mark.parametrize("flags, named, said", [
    (["--kernel", "gaussian", "--k", "4"], "--k", "no method of the grid is learned"),
    (["--k", "2"], "--k", "no method of the grid is learned"),  # the plain Gaussian grid
    (["--preset", "bench_quick", "--weights", "none"], "--weights", "add --kernel learned"),
    (["--stability", "--kernel", "beta"], "--kernel", "--stability runs its own"),
    (["--stability", "--budget", "100", "--budget", "200"], "--budget", "one budget"),
])
def test_grid_flag_that_would_change_nothing(flags, named, said, scene, tmp_path):
    """A flag the grid has no use for stops the bench before any run (it was silently dropped:
    `--kernel gaussian --k 4` benched the Gaussian alone)."""
    res = CliRunner().invoke(cli, ["bench", str(scene), "--out", str(tmp_path / "b"), *flags])
    assert res.exit_code == 2 and named in res.stderr and said in res.stderr, res.output
    assert not (tmp_path / "b").exists()


def test_k_without_kernel_flags_applies_to_the_bench_files_learned_methods():
    """--k alone re-sets the k of a bench file's learned methods: allowed when it has some."""
    methods = [{"kernel": "gaussian"}, {"kernel": "learned", "k": 8}]
    flags = dict(kernel=(), ks=("2",), weights=None, color=(), budget=(), budget_bytes=(), only=(), stability=False)
    check_grid_flags(**flags, methods=methods)
    with pytest.raises(click.BadParameter, match="no method of the grid is learned"):
        check_grid_flags(**flags, methods=methods[:1])


def test_bad_scene_is_one_line_error(tmp_path):
    res = CliRunner().invoke(cli, ["bench", str(tmp_path / "nope"), "--out", str(tmp_path / "o"),
                                   "--kernel", "gaussian"])
    assert res.exit_code == 2 and "does not exist" in res.stderr


def test_only_runs_the_matching_columns_of_a_preset(scene, tmp_path):
    res = _bench(scene, "--out", tmp_path, "--preset", "paper_tab5", "--only", "learned-k8-nopre*",
                 "--only", "learned-k2-precosine*", "--iters", "2", "--budget", "50", "--threads", "1",
                 "--metrics", "psnr", "-q")
    ran = sorted(p.name for p in (tmp_path / "results").glob("*.json"))
    assert ran == ["demo__learned-k2-precosine-sh-b50.json", "demo__learned-k8-nopre-sh-b50.json"], ran
    assert "not paper Tab. 5's protocol" in res.stderr
    bad = CliRunner().invoke(cli, ["bench", str(scene), "--out", str(tmp_path / "b"), "--preset", "paper_tab5",
                                   "--only", "nothing-*"])
    assert bad.exit_code == 2 and "no method id matches nothing-*" in bad.stderr and "learned-k8-nopre" in bad.stderr
    bad = CliRunner().invoke(cli, ["bench", str(scene), "--out", str(tmp_path / "c"), "--stability", "--only", "x*"])
    assert bad.exit_code == 2 and "--stability runs its own" in bad.stderr
