"""Option rules: a setting's type and range, checked with one error format.

A rule is a small tuple: ``int_range(lo, hi)``, ``float_range(lo, hi, lo_open)``,
``choice(*values)`` or ``BOOL``. :func:`option_error` words the one-line error the CLI prints:
``splatk: error: --sh-degree 7 (from the preset fast.yaml): must be ... (give ...)``.
"""
from __future__ import annotations

import math
import re

from .errors import InputError

BOOL = ("bool",)


def int_range(lo, hi=None):
    """A whole number (not a bool) from ``lo`` to ``hi`` (None: no upper end)."""
    return ("int", lo, hi)


def float_range(lo, hi=None, lo_open=False):
    """A finite number from ``lo`` (excluded when ``lo_open``) to ``hi``."""
    return ("float", lo, hi, lo_open)


def choice(*values):
    """One of the given strings."""
    return ("choice", values)


def describe(rule) -> str:
    kind = rule[0]
    if kind == "choice":
        return "one of " + ", ".join(map(str, rule[1]))
    if kind == "bool":
        return "true or false"
    lo, hi = rule[1], rule[2]
    what, fmt = ("a whole number", "{:,}") if kind == "int" else ("a number", "{:g}")
    if hi is None:
        return f"{what} {'above' if kind == 'float' and rule[3] else 'of at least'} {fmt.format(lo)}"
    return f"{what} from {fmt.format(lo)} to {fmt.format(hi)}"


def valid(value, rule) -> bool:
    kind = rule[0]
    if kind == "choice":
        return isinstance(value, str) and value in rule[1]
    if kind == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == "int":
        if not isinstance(value, int):
            return False
    elif not isinstance(value, (int, float)) or not math.isfinite(value):
        return False
    lo, hi = rule[1], rule[2]
    if kind == "float" and rule[3] and value <= lo:
        return False
    return value >= lo and (hi is None or value <= hi)


def what_is_wrong(value, rule) -> str:
    """Why ``value`` fails ``rule``, in the words of the error line (the fix then names the rule)."""
    kind = rule[0]
    if kind == "choice":
        return "not a known value"
    if kind == "bool":
        return "not true or false"
    numeric = isinstance(value, int) if kind == "int" else isinstance(value, (int, float))
    if isinstance(value, bool) or not numeric:
        return "not a whole number" if kind == "int" else "not a number"
    return "out of range" if math.isfinite(value) else "not a finite number"


def option_error(name: str, value, problem: str, fix: str, source: str | None = None) -> InputError:
    where = f" (from the {source})" if source and source not in ("default", "command line") else ""
    # a float as the user typed it ("0", not click's "0.0")
    shown = f"{value:g}" if isinstance(value, float) and math.isfinite(value) else repr(value)
    return InputError(None, f"--{name.replace('_', '-')} {shown}{where}: {problem}", fix)


def check_value(name: str, value, rule, sources: dict | None = None) -> None:
    """InputError unless ``value`` satisfies ``rule`` (``name``: the flag, without dashes)."""
    if not valid(value, rule):
        raise option_error(name, value, what_is_wrong(value, rule), f"give {describe(rule)}",
                           (sources or {}).get(name))


def parse_bytes(value) -> int:
    """4194304, "4MB", "512KB", "1.5GB" -> bytes (K/M/G are powers of 1024, as footprint_mb)."""
    if isinstance(value, bool):
        raise ValueError(f"cannot read byte size {value!r} (examples: 4194304, 4MB, 512KB)")
    if isinstance(value, (int, float)) and math.isfinite(value):
        return int(value)
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kmg]?)(i?b)?\s*", str(value).lower())
    if not m:
        raise ValueError(f"cannot read byte size {value!r} (examples: 4194304, 4MB, 512KB)")
    return int(float(m.group(1)) * {"": 1, "k": 2**10, "m": 2**20, "g": 2**30}[m.group(2)])


_DURATION = re.compile(r"(\d+(?:\.\d+)?)\s*([hms]?)")


def parse_duration(text) -> float | None:
    """'10m', '90s', '1h30m', '600' (seconds) -> seconds."""
    if text is None:
        return None
    if isinstance(text, bool):
        raise ValueError(f"cannot read duration {text!r} (examples: 10m, 90s, 1h30m)")
    if isinstance(text, (int, float)):
        return float(text)
    s = str(text).strip().lower().replace(" ", "")
    if not s:
        return None
    total, pos = 0.0, 0
    for m in _DURATION.finditer(s):
        if m.start() != pos:
            break
        total += float(m.group(1)) * {"h": 3600, "m": 60, "s": 1, "": 1}[m.group(2)]
        pos = m.end()
    if pos != len(s):
        raise ValueError(f"cannot read duration {text!r} (examples: 10m, 90s, 1h30m)")
    return total
