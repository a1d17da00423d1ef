"""A splats.bin header's sizes are claims: `splatk image-decode` checks them against the file's
length (and the pixel / table limits) before it reads the payload or allocates a model."""
from __future__ import annotations

import struct
import time
import tracemalloc

import pytest
from click.testing import CliRunner

from splatk.image import file as image_file
from splatk.image.kernels import KERNELS
from splatk.image.file import HEADER_BYTES, MAGIC, MAX_GRID, MAX_PIXELS, VERSION, payload_bytes
from splatk_cli.main import cli

HEADER = struct.Struct("<6sBBIHHBBH")  # the file format's header, as its docstring states it


def header(kernel="gaussian", n=1, height=8, width=8, grid=8, latent_dim=0, entries=0) -> bytes:
    return HEADER.pack(MAGIC, VERSION, KERNELS.index(kernel), n, height, width, grid, latent_dim, entries)


def test_header_layout_is_the_documented_one():
    assert HEADER.size == HEADER_BYTES == 20


CRAFTED = {
    # 8 KiB file claiming 2^32 - 1 splats (tens of GB of parameters)
    "huge_count": header(n=0xFFFFFFFF) + bytes(8192),
    # a gabor file one splat short: the count does not match the length
    "count_past_length": header("gabor", n=101) + bytes(payload_bytes("gabor", 100, 0, 0)),
    # exactly the payload one splat needs, but a 65535 x 65535 image (51 GB to draw)
    "huge_image": header(n=1, height=0xFFFF, width=0xFFFF) + bytes(payload_bytes("gaussian", 1, 0, 0)),
    # a learned table of 255 x 255 nodes per splat
    "huge_grid": header("learned", n=4, grid=255, latent_dim=2) + bytes(payload_bytes("learned", 4, 2, 0)),
    # a palette larger than a one-byte index reaches
    "huge_palette": header("learned", n=4, latent_dim=2, entries=300) + bytes(4096),
    # latents declared for a kernel that has none
    "latents_for_gaussian": header(n=1, latent_dim=9) + bytes(payload_bytes("gaussian", 1, 0, 0)),
}


@pytest.mark.parametrize("name", list(CRAFTED))
def test_crafted_header_is_one_line_error_before_allocating(tmp_path, monkeypatch, name):
    path = tmp_path / f"{name}.bin"
    path.write_bytes(CRAFTED[name])

    def no_model(*args, **kwargs):
        raise AssertionError("a model was allocated from an unchecked header")

    monkeypatch.setattr(image_file, "Splats2D", no_model)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        res = CliRunner().invoke(cli, ["image-decode", str(path), "--out", str(tmp_path / "out.png")])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and "Traceback" not in res.output, res.output
    assert lines[0].startswith(f"splatk: error: {path}: "), lines[0]
    assert time.perf_counter() - t0 < 5.0
    assert peak < 4 * 2**20, peak
    assert not (tmp_path / "out.png").exists()


def test_limits_allow_what_splatk_image_makes():
    assert MAX_PIXELS >= 7000 * 7000 and MAX_GRID >= 8


def test_valid_header_and_length_still_load(tmp_path):
    n = 3
    path = tmp_path / "ok.bin"
    path.write_bytes(header("gabor", n=n, height=5, width=7) + bytes(payload_bytes("gabor", n, 0, 0)))
    model = image_file.load_splats2d(path)
    assert (model.kernel, model.n, model.height, model.width) == ("gabor", n, 5, 7)
