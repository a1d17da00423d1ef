"""Shared CLI plumbing: presets, value parsing, error reporting. No engine logic here."""
from __future__ import annotations

import signal
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import click
from click.core import ParameterSource

from splatk.errors import InputError
from splatk.yaml_files import read_yaml_file


def _preset_dirs() -> list[Path]:
    """Where named presets live: ``splatk_cli/presets`` in a wheel (pyproject.toml maps the
    top-level ``presets/`` there), the repository's ``presets/`` in a source tree or an
    editable install."""
    here = Path(__file__).resolve().parent
    dirs = [here / "presets"]
    if (here.parent / "pyproject.toml").is_file():  # a source tree, not site-packages
        dirs.append(here.parent / "presets")
    return [d for d in dirs if d.is_dir()]


PRESET_DIRS = _preset_dirs()


def find_preset(name: str) -> Path:
    p = Path(name)
    if p.is_file():
        return p
    for d in PRESET_DIRS:
        for cand in (d / name, d / f"{name}.yaml"):
            if cand.is_file():
                return cand
    names = sorted({c.stem for d in PRESET_DIRS for c in d.glob("*.yaml")})
    raise InputError(name, "no such file, nor a preset of that name",
                     f"give a YAML file's path or a preset: {', '.join(names)}")


def load_preset(name: str | None) -> tuple[dict, Path | None]:
    """(option values, file) of a preset; ({}, None) without one."""
    if not name:
        return {}, None
    path = find_preset(name)
    data = read_yaml_file(path, "preset") or {}
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise InputError(path, "a preset is a mapping of option names to values", "e.g. iters: 2000")
    return {k.replace("-", "_"): v for k, v in data.items()}, path


def resolve_options(ctx: click.Context, params: dict, preset: dict,
                    preset_path: Path | None = None) -> tuple[dict, dict]:
    """Merge command line > SPLATK_* environment > preset > default.

    Returns (values, sources) for every option in ``params``; options left at None mean
    "use the engine's default". Preset values pass through the same click types as the
    command line's (an InputError naming the preset when one does not fit); ranges are checked
    by the engine, whatever the source.
    """
    by_name = {p.name: p for p in ctx.command.params}
    where = f"preset {preset_path}" if preset_path else "preset"
    unknown = sorted(set(preset) - set(params))
    if unknown:
        raise InputError(preset_path, f"unknown option {unknown[0]!r}",
                         f"see `splatk {ctx.command.name} --help` for the options")
    values, sources = {}, {}
    for name, value in params.items():
        src = ctx.get_parameter_source(name)
        if src in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT):
            values[name], sources[name] = value, "command line" if src == ParameterSource.COMMANDLINE else "environment"
        elif name in preset and preset[name] is not None:
            values[name], sources[name] = _typed(ctx, by_name[name], preset[name], preset_path), where
        else:
            values[name], sources[name] = value, "default"
    return values, sources


def _typed(ctx: click.Context, param: click.Parameter, value, preset_path: Path | None):
    """A preset value converted by the option's click type, as a typed flag would be."""
    if isinstance(value, (dict, list)) or (isinstance(value, bool) and not param.is_flag
                                           and not isinstance(param.type, click.types.BoolParamType)):
        raise InputError(preset_path, f"{param.name}: {value!r} is not a single value",
                         f"see `splatk {ctx.command.name} --help`")
    try:
        return param.type.convert(value, param, ctx)
    except click.BadParameter as e:
        raise InputError(preset_path, f"{param.name}: {e.format_message()}",
                         f"see `splatk {ctx.command.name} --help`") from None


def fail(message: str, code: int = 2) -> None:
    click.echo(f"splatk: error: {message}", err=True)
    sys.exit(code)


@contextmanager
def stop_requests(at_once: Callable[[], bool] = lambda: False) -> Iterator[dict]:
    """Turn SIGTERM (a scheduler's or `timeout`'s stop) and the first Ctrl-C into a request that
    long work polls at its next iteration boundary, so the checkpoint it then saves holds whole
    iterations (a KeyboardInterrupt can land inside density control, between two tensors'
    updates). A second Ctrl-C, or one while ``at_once()`` is true, interrupts at once.

    Yields ``{"signal": None}``; ``"signal"`` becomes the signal's number once one asks to stop.
    pycolmap installs glog's handler (a stack dump, then death) for SIGTERM when it is first
    imported, and the last handler installed wins: splatk.data imports it before any command
    runs, so this one is installed after it (tests/cli/test_signals.py sends the real signal).
    """
    state: dict = {"signal": None}

    def handle(signum, frame):
        if signum == signal.SIGINT and (state["signal"] is not None or at_once()):
            raise KeyboardInterrupt
        state["signal"] = signum

    old_term = signal.signal(signal.SIGTERM, handle)
    old_int = signal.signal(signal.SIGINT, handle)
    try:
        yield state
    finally:
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGINT, old_int)


def signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
