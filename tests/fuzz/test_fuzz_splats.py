"""Fuzzed ``splats.bin`` files: ``load_splats2d`` returns a model or raises InputError, within
the hypothesis deadline and the memory cap of conftest.py.

Inputs: random bytes, the real file truncated, byte-flipped or with random header fields
(kernel, count, size, grid, latent size, palette entries), written by ``splatk image`` for a
tiny model of each kernel.
"""
from __future__ import annotations

import struct
import tempfile
from functools import lru_cache
from pathlib import Path

import pytest
import torch
from hypothesis import event, given, settings
from hypothesis import strategies as st

from splatk.errors import InputError
from splatk.models.image2d import KERNELS, Splats2D
from splatk.models.image2d_io import HEADER_BYTES, MAGIC, encode_splats2d, load_splats2d


@lru_cache(maxsize=1)
def valid_files() -> dict[str, bytes]:
    out = {}
    for kernel in KERNELS:
        model = Splats2D(kernel, 4, 8, 8, grid=2, generator=torch.Generator().manual_seed(0))
        if kernel == "learned":
            model.round_shared()
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


# the header's count, size and palette fields are not yet checked before the model is allocated
# (a count of 2**32 asks torch for 100 GB; 257 palette entries reach Splats2D's ValueError);
# image2d_io.py is being fixed, after which this marker goes
@pytest.mark.xfail(raises=(RuntimeError, ValueError, MemoryError), strict=False,
                   reason="splats.bin header fields not validated before allocation")
@settings(report_multiple_bugs=False)
@given(data=st.data())
def test_splat_file(data):
    files = valid_files()
    raw = bytearray(files[data.draw(st.sampled_from(sorted(files)))])
    kind = data.draw(st.sampled_from(["header", "header", "random", "truncate", "flip"]))
    if kind == "random":
        raw = bytearray(data.draw(st.one_of(st.binary(max_size=300), st.binary(max_size=300).map(MAGIC.__add__))))
    elif kind == "truncate":
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    elif kind == "flip":
        for _ in range(data.draw(st.integers(1, 6))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    else:
        names = data.draw(st.lists(st.sampled_from(sorted(HEADER_FIELDS)), min_size=1, max_size=3, unique=True))
        for name in names:
            offset, fmt, values = HEADER_FIELDS[name]
            struct.pack_into(fmt, raw, offset, data.draw(values))
        assert len(raw) >= HEADER_BYTES
    with tempfile.TemporaryDirectory(prefix="splatk-fuzz-") as tmp:
        path = Path(tmp) / "splats.bin"
        path.write_bytes(bytes(raw))
        try:
            model = load_splats2d(path)
        except InputError:
            event(f"{kind}: refused")
        else:
            assert model.n >= 1 and model.height >= 1 and model.width >= 1
            event(f"{kind}: ok")
