"""Shared CLI plumbing: presets, value parsing, error reporting. No engine logic here."""
from __future__ import annotations

import re
import sys
from pathlib import Path

import click
import yaml
from click.core import ParameterSource

PRESET_DIRS = [Path(__file__).resolve().parent.parent / "presets"]


def find_preset(name: str) -> Path:
    p = Path(name)
    if p.is_file():
        return p
    for d in PRESET_DIRS:
        for cand in (d / name, d / f"{name}.yaml"):
            if cand.is_file():
                return cand
    raise click.BadParameter(f"preset {name!r} not found (looked in {', '.join(map(str, PRESET_DIRS))})")


def load_preset(name: str | None) -> dict:
    if not name:
        return {}
    path = find_preset(name)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise click.BadParameter(f"{path}: invalid YAML ({e})") from e
    if not isinstance(data, dict):
        raise click.BadParameter(f"{path}: a preset is a mapping of option names to values")
    return {k.replace("-", "_"): v for k, v in data.items()}


def resolve_options(ctx: click.Context, params: dict, preset: dict) -> tuple[dict, dict]:
    """Merge command line > SPLATK_* environment > preset > default.

    Returns (values, sources) for every option in ``params``; options left at None mean
    "use the engine's default".
    """
    values, sources = {}, {}
    for name, value in params.items():
        src = ctx.get_parameter_source(name)
        if src in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT):
            values[name], sources[name] = value, "command line" if src == ParameterSource.COMMANDLINE else "environment"
        elif name in preset:
            values[name], sources[name] = preset[name], "preset"
        else:
            values[name], sources[name] = value, "default"
    unknown = set(preset) - set(params)
    if unknown:
        raise click.BadParameter(f"preset has unknown options: {', '.join(sorted(unknown))}")
    return values, sources


_DUR = re.compile(r"(\d+(?:\.\d+)?)\s*([hms]?)")


def parse_duration(text: str | float | int | None) -> float | None:
    """'10m', '90s', '1h30m', '600' (seconds) -> seconds."""
    if text is None:
        return None
    if isinstance(text, (int, float)):
        return float(text)
    s = str(text).strip().lower().replace(" ", "")
    if not s:
        return None
    total, pos = 0.0, 0
    for m in _DUR.finditer(s):
        if m.start() != pos:
            break
        total += float(m.group(1)) * {"h": 3600, "m": 60, "s": 1, "": 1}[m.group(2)]
        pos = m.end()
    if pos != len(s):
        raise click.BadParameter(f"cannot read duration {text!r} (examples: 10m, 90s, 1h30m)")
    return total


def fail(message: str, code: int = 2) -> None:
    click.echo(f"splatk: error: {message}", err=True)
    sys.exit(code)
