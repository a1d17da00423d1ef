"""Property: whatever values a user gives `splatk fit`'s settings (command line, environment,
preset, resumed config: they all meet in fit_config_from_options and check_fit_config), the
result is a checked FitConfig or one InputError, never another exception; and through the real
CLI, a rejected option changes no file outside --out and leaves an existing run as it was."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from splatk.errors import InputError
from splatk.stages.fit_config import RULES, check_fit_config, fit_config_from_options
from splatk_cli.main import cli

#: every flat name the translator reads
NAMES = sorted({name for _, name, _ in RULES} | {"kernel", "k", "budget", "budget_bytes", "time_budget", "backend",
                                                  "device", "background", "kernel_weights", "init"})

values = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-2**70, max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["auto", "auto:0", "auto:-5", "1e12", "4MB", "0", "-1", "nan", "inf", "10m", "0s", "learned",
                     "gaussian", "planar", "sb", "sh", "cpu", "torch", "cuda", "random", "sfm", "1e400", "", " "]),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.dictionaries(st.sampled_from(["k", "freeze_iters", "weights", "net_lr_mult", "nope"]),
                    st.one_of(st.integers(-5, 10), st.text(max_size=4), st.none()), max_size=3),
)
options = st.dictionaries(st.sampled_from(NAMES + ["kernel_options", "unknown_setting"]), values, max_size=6)


@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(options)
def test_any_option_values_give_a_config_or_one_input_error(opts):
    try:
        cfg, _ = fit_config_from_options(opts, {k: "preset test.yaml" for k in opts})
        check_fit_config(cfg)
    except InputError as e:
        assert e.message() and "\n" not in e.message()


def test_every_setting_a_preset_names_is_checked():
    """Each flat setting has a rule, or is checked by building what it names; a setting with
    neither reaches training as given (``relocate_one_view: maybe`` once did)."""
    from splatk.stages.fit_config import _FIT_FIELDS, _TRAIN_FIELDS

    checked_by_building = {"adc", "backend", "background", "device", "kernel", "kernel_options"}
    assert (_FIT_FIELDS | _TRAIN_FIELDS) - {name for _, name, _ in RULES} - checked_by_building == set()
    for name in ("relocate_one_view", "hold_growth", "random_background"):
        with pytest.raises(InputError, match=name.replace("_", "-")):
            check_fit_config(fit_config_from_options({name: "maybe"}, {name: "preset test.yaml"})[0])


def tree_digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode() + p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A scene, a finished run and a bystander file, all of which rejected commands must keep."""
    from splatk.data.synthetic import make_demo_scene

    root = tmp_path_factory.mktemp("world")
    scene = make_demo_scene(root / "scene", num_views=6, size=24)
    run = root / "run"
    res = CliRunner().invoke(cli, ["fit", str(scene), "--out", str(run), "--iters", "5", "--budget", "50",
                                   "--backend", "torch", "-q"])
    assert res.exit_code == 0, res.output
    (root / "bystander.txt").write_text("not splatk's")
    return root, scene, run


FLAG_VALUES = st.sampled_from(["0", "-1", "-3", "1e12", "1e400", "nan", "inf", "abc", "", "7", "2", "100000", "0.001",
                               "auto:0", "10x"])
FLAGS = ["--budget", "--sh-degree", "--threads", "--downscale", "--checkpoint-every", "--seed",
         "--time-budget", "--k", "--budget-bytes"]


#: each example may run `splatk fit` for an iteration: fewer than the loader tests
CLI_EXAMPLES = 400 if os.environ.get("SPLATK_FUZZ_PROFILE") == "long" else 40


@settings(deadline=None, max_examples=CLI_EXAMPLES, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.sampled_from(FLAGS), FLAG_VALUES), min_size=1, max_size=3))
def test_rejected_flags_touch_nothing(world, flags):
    root, scene, run = world
    before, scene_before = tree_digest(root), tree_digest(scene)
    args = ["fit", str(scene), "--out", str(run), "--overwrite", "--backend", "torch", "-q"]
    for flag, value in flags:
        args += [flag, value]
    args += ["--iters", "1"]  # the last one wins: a valid combination trains one iteration
    res = CliRunner().invoke(cli, args)
    assert "Traceback" not in res.output
    assert (root / "bystander.txt").read_text() == "not splatk's" and tree_digest(scene) == scene_before
    if res.exit_code != 0:  # click's type errors and splatk's range errors alike: exit 2, nothing changed
        assert res.exit_code == 2, res.output
        assert tree_digest(root) == before
