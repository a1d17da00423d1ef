"""Reading a YAML file a user wrote (a preset, a bench file): any fault is one InputError line."""
from __future__ import annotations

from pathlib import Path

import yaml

from .errors import InputError


def describe_yaml_error(error: yaml.YAMLError) -> str:
    """A YAML parser's error in one line: where in the file and what the parser found there
    (PyYAML's own text spreads the quoted input over several lines)."""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    mark = getattr(error, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return f"{where}{problem}"


def read_yaml_file(path: Path, kind: str):
    """The parsed document of ``path`` (None for an empty file); ``kind`` names the file in the
    fix, e.g. "preset" or "bench file"."""
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise InputError(path, f"invalid YAML ({describe_yaml_error(e)})", f"fix the {kind}") from None
    except UnicodeDecodeError:
        raise InputError(path, "is not UTF-8 text", f"save the {kind} as UTF-8") from None
