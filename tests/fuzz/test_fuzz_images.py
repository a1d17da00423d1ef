"""Fuzzed image files: load_scene (decoding the images) returns a valid Scene or raises InputError.

Images become random bytes, truncated PNG / JPEG, PNGs with random header fields (size, bit
depth, colour type; CRC fixed or not), JPEGs with a patched frame size, or byte-flipped copies.
The memory cap of conftest.py makes any decode past the loader's own pixel cap a failure.
"""
from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
from fuzz_helpers import loads_or_refuses, scene_copy
from hypothesis import event, given
from hypothesis import strategies as st

SIZES = st.one_of(st.sampled_from([0, 1, 16, 12, 65535, 65536, 100_000, 2**31 - 1, 2**32 - 1]),
                  st.integers(0, 2**32 - 1))


def _png_with_header(width: int, height: int, depth: int, colour: int, fix_crc: bool, payload: bytes) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    crc = zlib.crc32(b"IHDR" + ihdr) if fix_crc else 0

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", crc)
            + chunk(b"IDAT", zlib.compress(payload)) + chunk(b"IEND", b""))


@st.composite
def image_bytes(draw, original: bytes) -> bytes:
    kind = draw(st.sampled_from(["random", "truncated", "png_header", "jpeg_size", "flipped", "jpeg_truncated"]))
    event(kind)
    if kind == "random":
        return draw(st.binary(max_size=512))
    if kind == "truncated":
        return original[:draw(st.integers(0, len(original)))]
    if kind == "png_header":
        return _png_with_header(draw(SIZES), draw(SIZES), draw(st.sampled_from([1, 2, 4, 8, 16, 0, 3, 255])),
                                draw(st.sampled_from([0, 2, 3, 4, 6, 1, 7])), draw(st.booleans()),
                                draw(st.binary(max_size=256)))
    jpeg = cv2.imencode(".jpg", np.full((12, 16, 3), 128, np.uint8))[1].tobytes()
    if kind == "jpeg_truncated":
        return jpeg[:draw(st.integers(0, len(jpeg)))]
    if kind == "jpeg_size":
        data = bytearray(jpeg)
        struct.pack_into(">HH", data, data.index(b"\xff\xc0") + 5, draw(st.integers(0, 65535)),
                         draw(st.integers(0, 65535)))
        return bytes(data)
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 6))):
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    return bytes(data)


@given(data=st.data())
def test_transforms_images(demo_base, data):
    with scene_copy(demo_base) as (scene, outside):
        path = scene / "train" / data.draw(st.sampled_from(["r_1.png", "r_2.png"]))
        path.write_bytes(data.draw(image_bytes(path.read_bytes())))
        event(loads_or_refuses(scene, outside, load_images=True))


@given(data=st.data())
def test_colmap_images(colmap_bin_base, data):
    with scene_copy(colmap_bin_base) as (scene, outside):
        path = scene / "images" / "img_02.png"
        path.write_bytes(data.draw(image_bytes(path.read_bytes())))
        event(loads_or_refuses(scene, outside, load_images=True))
