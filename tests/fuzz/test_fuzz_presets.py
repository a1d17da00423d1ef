"""Fuzzed preset files: ``load_preset`` returns a mapping of option names or raises one
InputError naming the file (exit code 2 through the CLI). Only the parsing is fuzzed here; what
the options' values mean is checked by the schema's own property test (test_fit_options.py).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import event, given
from hypothesis import strategies as st

from splatk.errors import InputError
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
            preset, found = load_preset(str(path))
        except InputError as e:
            assert str(path) in e.message() and "\n" not in e.message(), e.message()
            return "refused"
        assert found == path and isinstance(preset, dict) and all(isinstance(k, str) for k in preset), preset
        return "ok"


@given(doc=st.dictionaries(st.one_of(OPTION_NAMES, st.integers(), st.none(), st.booleans()), VALUES, max_size=6))
def test_structured_presets(doc):
    event(_load(yaml.safe_dump(doc, allow_unicode=True)))


@given(parts=st.lists(st.one_of(YAML_SNIPPETS, st.text(max_size=30)), max_size=4))
def test_text_presets(parts):
    event(_load("".join(parts)))


@given(raw=st.binary(max_size=64))
def test_raw_byte_presets(raw):
    event(_load(raw))


@pytest.mark.parametrize("text", ["1: 2\n", "null: 3\n"])
def test_non_string_key_is_refused(text):
    assert _load(text) == "refused"


def test_non_utf8_preset_is_refused():
    assert _load(b"iters: \xff\n") == "refused"
