"""Every shipped preset loads and resolves to a valid fit configuration."""
from pathlib import Path

import pytest

from splatk_cli.common import load_preset, parse_duration
from splatk_cli.fit import build_fit_config

PRESETS = sorted((Path(__file__).resolve().parents[2] / "presets").glob("*.yaml"))


@pytest.mark.parametrize("path", PRESETS, ids=[p.stem for p in PRESETS])
def test_preset_loads(path):
    data = load_preset(str(path))
    assert isinstance(data, dict) and data
    cfg = build_fit_config(data)
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
    import click

    with pytest.raises(click.BadParameter):
        parse_duration("ten minutes")
