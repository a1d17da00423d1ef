"""Fuzzed COLMAP models: load_scene returns a valid Scene or raises InputError, nothing else.

Text models (cameras.txt, images.txt, points3D.txt) get token- and line-level edits with values
chosen to break parsers (huge integers, NaN, negative sizes, unknown models, paths leaving the
image folder); binary models get random bytes, truncation, and interesting integers and doubles
written over their fields.
"""
from __future__ import annotations

import math
import struct

from fuzz_helpers import loads_or_refuses, scene_copy
from hypothesis import event, given
from hypothesis import strategies as st

MODEL_FILES = ["cameras", "images", "points3D"]
TOKENS = st.one_of(
    st.sampled_from(["0", "-1", "1", "2", "3", "nan", "inf", "-inf", "1e39", "-1e39", "1e-320", "1e308",
                     "99999999999999999999", "-9223372036854775809", "4294967297", "0x10", "1.5", "-0",
                     "PINHOLE", "SIMPLE_RADIAL", "OPENCV", "FULL_OPENCV", "FOV", "img_01.png", "img_02.png",
                     "../outside/photo.png", "/etc/passwd", "..", "#", "a\x00b"]),
    st.integers(-(2**70), 2**70).map(str),
    st.floats().map(repr),
    st.text(alphabet=st.characters(blacklist_categories=["Cs"]), min_size=1, max_size=8),
)


@st.composite
def text_edits(draw, lines: list[str]):
    lines = list(lines)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["replace", "delete_token", "insert_token", "delete_line", "dup_line",
                                   "insert_line", "truncate"]))
        if not lines:
            lines = [""]
        i = draw(st.integers(0, len(lines) - 1))
        tok = lines[i].split(" ")
        j = draw(st.integers(0, len(tok) - 1))
        if op == "replace":
            tok[j] = draw(TOKENS)
        elif op == "delete_token":
            del tok[j]
        elif op == "insert_token":
            tok.insert(j, draw(TOKENS))
        if op in ("replace", "delete_token", "insert_token"):
            lines[i] = " ".join(tok)
        elif op == "delete_line":
            del lines[i]
        elif op == "dup_line":
            lines.insert(i, lines[i])
        elif op == "insert_line":
            lines.insert(i, " ".join(draw(st.lists(TOKENS, min_size=1, max_size=12))))
        else:
            lines = lines[:i] + [lines[i][:draw(st.integers(0, len(lines[i])))]]
    return lines


@given(data=st.data(), load_images=st.booleans())
def test_text_model(colmap_text_base, data, load_images):
    with scene_copy(colmap_text_base) as (scene, outside):
        for name in data.draw(st.lists(st.sampled_from(MODEL_FILES), min_size=1, max_size=2, unique=True)):
            path = scene / "sparse" / "0" / f"{name}.txt"
            path.write_text("\n".join(data.draw(text_edits(path.read_text().splitlines()))) + "\n")
        event(loads_or_refuses(scene, outside, load_images=load_images))


FIELD_VALUES = st.one_of(
    st.tuples(st.just("<q"), st.sampled_from([0, -1, 1, 2, 3, 1000, 2**31, 2**40, 2**62, 2**63 - 1, -(2**63)])),
    st.tuples(st.just("<i"), st.sampled_from([0, -1, 1, 2, 3, 4, 5, 99, 2**31 - 1, -(2**31)])),
    st.tuples(st.just("<d"), st.sampled_from([0.0, -1.0, -50.0, 1e6, 1e39, 1e308, 1e-320, math.nan, math.inf,
                                              -math.inf])),
    st.tuples(st.just("<B"), st.integers(0, 255)),
)


@given(data=st.data(), load_images=st.booleans())
def test_binary_model(colmap_bin_base, data, load_images):
    with scene_copy(colmap_bin_base) as (scene, outside):
        name = data.draw(st.sampled_from(MODEL_FILES))
        path = scene / "sparse" / "0" / f"{name}.bin"
        raw = bytearray(path.read_bytes())
        kind = data.draw(st.sampled_from(["fields", "fields", "random", "truncate", "append", "splice"]))
        if kind == "random":
            raw = bytearray(data.draw(st.binary(max_size=600)))
        elif kind == "truncate":
            raw = raw[:data.draw(st.integers(0, len(raw)))]
        elif kind == "append":
            raw += data.draw(st.binary(min_size=1, max_size=64))
        elif kind == "splice":
            i = data.draw(st.integers(0, len(raw)))
            raw[i:i] = data.draw(st.binary(min_size=1, max_size=32))
        else:
            for _ in range(data.draw(st.integers(1, 3))):
                fmt, value = data.draw(FIELD_VALUES)
                size = struct.calcsize(fmt)
                if len(raw) >= size:
                    struct.pack_into(fmt, raw, data.draw(st.integers(0, len(raw) - size)), value)
        path.write_bytes(bytes(raw))
        event(f"{name} {kind}: {loads_or_refuses(scene, outside, load_images=load_images)}")
