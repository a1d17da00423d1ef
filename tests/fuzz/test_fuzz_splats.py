"""Fuzzed ``splats.bin`` files: ``load_splats2d`` returns a model or raises InputError, within
the hypothesis deadline and the memory cap of conftest.py.

Inputs start from the file ``splatk image`` writes for a tiny model of each kernel: its payload
truncated, byte-flipped or replaced, or its header fields set at random (the latter test is
checked against the file's length and limits before anything is allocated).
"""
from __future__ import annotations

import struct
import tempfile
from functools import lru_cache
from pathlib import Path

import torch
from hypothesis import event, given, settings
from hypothesis import strategies as st

from splatk.errors import InputError
from splatk.image.kernels import KERNELS
from splatk.image.model import Splats2D
from splatk.image.file import HEADER_BYTES, MAGIC, encode_splats2d, load_splats2d


@lru_cache(maxsize=1)
def valid_files() -> dict[str, bytes]:
    out = {}
    for kernel in KERNELS:
        model = Splats2D(kernel, 4, 8, 8, grid=2, generator=torch.Generator().manual_seed(0))
        model.round_shared()  # the learned kernels' decoders are stored at float16; others: no-op
        out[kernel] = encode_splats2d(model)
    return out


U32 = st.one_of(st.sampled_from([0, 1, 2, 4, 255, 65535, 2**31, 2**32 - 1]), st.integers(0, 2**32 - 1))
HEADER_FIELDS = {  # name: (offset, struct format, values)
    "version": (6, "<B", st.integers(0, 255)),
    "kernel": (7, "<B", st.integers(0, 255)),
    "n": (8, "<I", U32),
    "height": (12, "<H", st.integers(0, 65535)),
    "width": (14, "<H", st.integers(0, 65535)),
    "grid": (16, "<B", st.integers(0, 255)),
    "latent_dim": (17, "<B", st.integers(0, 255)),
    "palette": (18, "<H", st.integers(0, 65535)),
}


def _load(raw: bytes, kind: str) -> None:
    with tempfile.TemporaryDirectory(prefix="splatk-fuzz-") as tmp:
        path = Path(tmp) / "splats.bin"
        path.write_bytes(raw)
        try:
            model = load_splats2d(path)
        except InputError:
            event(f"{kind}: refused")
        else:
            assert model.n >= 1 and model.height >= 1 and model.width >= 1
            event(f"{kind}: ok")


@given(data=st.data())
def test_splat_file_payload(data):
    """The header as written, anything after it: random bytes after the magic, truncation, flips."""
    files = valid_files()
    raw = bytearray(files[data.draw(st.sampled_from(sorted(files)))])
    kind = data.draw(st.sampled_from(["random", "truncate", "flip", "append"]))
    if kind == "random":
        raw = raw[:HEADER_BYTES] + data.draw(st.binary(max_size=300))
    elif kind == "truncate":
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    elif kind == "append":
        raw += data.draw(st.binary(min_size=1, max_size=64))
    else:
        for _ in range(data.draw(st.integers(1, 6))):
            raw[data.draw(st.integers(HEADER_BYTES, len(raw) - 1))] = data.draw(st.integers(0, 255))
    _load(bytes(raw), kind)


@settings(report_multiple_bugs=False)
@given(data=st.data())
def test_splat_file_header(data):
    """Random header fields (kernel, count, size, grid, latent size, palette entries, version),
    or random bytes after the magic."""
    files = valid_files()
    raw = bytearray(files[data.draw(st.sampled_from(sorted(files)))])
    if data.draw(st.booleans()):
        raw = bytearray(MAGIC + data.draw(st.binary(max_size=300)))
        kind = "random"
    else:
        names = data.draw(st.lists(st.sampled_from(sorted(HEADER_FIELDS)), min_size=1, max_size=3, unique=True))
        for name in names:
            offset, fmt, values = HEADER_FIELDS[name]
            struct.pack_into(fmt, raw, offset, data.draw(values))
        kind = "header"
    _load(bytes(raw), kind)
