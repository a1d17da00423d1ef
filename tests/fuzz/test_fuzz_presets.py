"""Fuzzed preset files: ``load_preset`` returns a mapping of option names or raises click's
BadParameter (shown as a usage error, exit code 2). Only the parsing is fuzzed here; what the
options' values mean is checked by the fit command's own tests.

Two inputs ``load_preset`` does not yet refuse cleanly are pinned by the strict xfail tests at
the end (a non-string key, a file that is not UTF-8); the generators leave them out until those
tests pass, then they should widen to any key and raw bytes.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import click
import pytest
import yaml
from hypothesis import event, given
from hypothesis import strategies as st

from splatk_cli.common import load_preset

SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(), st.text(max_size=12))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                      st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                      max_leaves=10)
OPTION_NAMES = st.one_of(st.sampled_from(["iters", "kernel", "backend", "lr-scale", "sh_degree", "init", "threads",
                                          "max-time", ""]), st.text(max_size=12))
YAML_SNIPPETS = st.sampled_from([
    "iters: 100\n", "- a\n- b\n", "a: &x [1, 2]\nb: *x\n", "a: *missing\n", "!!python/object:os.system {}\n",
    "? [1, 2]\n: 3\n", "a: b: c\n", "\t- x\n", "%YAML 9.9\n---\na: 1\n", "a: 1\n---\nb: 2\n", "{", "'",
    "a: !!binary aGVsbG8=\n", "a: 1e999\n", "a: .nan\n", "<<: {iters: 5}\n", "",
])


def _load(text: str | bytes) -> str:
    with tempfile.TemporaryDirectory(prefix="splatk-fuzz-") as tmp:
        path = Path(tmp) / "preset.yaml"
        (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
        try:
            preset = load_preset(str(path))
        except click.BadParameter as e:
            assert str(path) in e.format_message() or "preset" in e.format_message(), e.format_message()
            return "refused"
        assert isinstance(preset, dict) and all(isinstance(k, str) for k in preset), preset
        return "ok"


@given(doc=st.dictionaries(OPTION_NAMES, VALUES, max_size=6))
def test_structured_presets(doc):
    event(_load(yaml.safe_dump(doc, allow_unicode=True)))


@given(parts=st.lists(st.one_of(YAML_SNIPPETS, st.text(max_size=30)), max_size=4))
def test_text_presets(parts):
    event(_load("".join(parts)))


KNOWN = "load_preset (cli/common.py) lets this escape as a traceback; the option-validation rewrite refuses it"


@pytest.mark.xfail(strict=True, raises=AttributeError, reason=KNOWN)
@pytest.mark.parametrize("text", ["1: 2\n", "null: 3\n"])
def test_non_string_key_is_refused(text):
    assert _load(text) == "refused"


@pytest.mark.xfail(strict=True, raises=UnicodeDecodeError, reason=KNOWN)
def test_non_utf8_preset_is_refused():
    assert _load(b"iters: \xff\n") == "refused"
