"""Niantic's SPZ, version 3 (the gzip container that web viewers and sharing sites read), written
from the format's specification and its reference implementation (nianticlabs/spz,
``load-spz.cc``), whose Python bindings on PyPI build only from source (CMake, zstd); for the
same inputs the payload is byte for byte the reference writer's.

The whole file is one gzip stream of a 16-byte header and six arrays, attribute by attribute:

* header ``<IIIBBBB``: magic ``NGSP`` (0x5053474E), version 3, N, SH degree, fractional bits
  F, flags (0: not antialiased), reserved.
* positions: N x 3 signed 24-bit fixed-point values (``round(x * 2^F)``), little-endian. F is
  12, as the reference writer sets it, unless a coordinate reaches 2^11 (a far background
  Gaussian): then the largest F that holds every coordinate; readers take F from the header.
* alphas: N bytes, ``255 sigmoid(opacity)``.
* colours: N x 3 bytes, ``f_dc * 0.15 * 255 + 127.5``.
* scales: N x 3 bytes, ``(log scale + 10) * 16``.
* rotations: N x 4 bytes, "smallest three": the index of the largest-magnitude component of the
  (x, y, z, w) quaternion in the top two bits of a little-endian uint32, then, for each other
  component in order, a sign bit and 9 bits of ``|q_i| / sqrt(1/2)`` (the largest is made positive).
* SH: N x K x 3 bytes (coefficient-major, channel-minor), ``round(128 c) + 128`` rounded to
  buckets of 8 (degree 1) or 16 (degrees 2, 3), the reference writer's defaults.

SPZ stores right-up-back (RUB, OpenGL) coordinates; splatk's models, like the 3DGS PLY, are
right-down-front (RDF, COLMAP), so the writer turns them 180 degrees about x: y and z of the
positions and of the quaternion's vector part change sign, and so does every SH coefficient
whose basis function is odd in y and z together (the reference implementation's table).
"""
from __future__ import annotations

import gzip
import math
import struct
from typing import BinaryIO

import numpy as np

from .gaussians import Gaussians

MAGIC = 0x5053474E  # "NGSP" little-endian
VERSION = 3
#: the reference writer's fractional bits of a position (1/4096 of a scene unit)
FRACTIONAL_BITS = 12
#: largest value of a signed 24-bit position
MAX_FIXED = 2**23 - 1
COLOR_SCALE = 0.15
#: RDF -> RUB sign of x, y, z of a position or a quaternion's vector part
FLIP_XYZ = np.array([1.0, -1.0, -1.0], np.float32)
#: RDF -> RUB sign of the 15 SH coefficients above DC (degrees 1-3, the 3DGS basis order)
FLIP_SH = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
#: SH quantisation bucket sizes: 5 bits for degree 1, 4 bits for degrees 2 and 3
SH1_BUCKET, SH_REST_BUCKET = 1 << (8 - 5), 1 << (8 - 4)


def _round(x: np.ndarray) -> np.ndarray:
    """C's ``round``: halves away from zero (numpy's rounds them to even)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(x), 0, 255).astype(np.uint8)


def fractional_bits(means: np.ndarray) -> int | None:
    """Fractional bits of the positions: :data:`FRACTIONAL_BITS`, or fewer where a coordinate
    needs more integer bits; None when one does not fit even with none."""
    largest = float(np.abs(means.astype(np.float64)).max()) if len(means) else 0.0
    for bits in range(FRACTIONAL_BITS, -1, -1):
        if _round(np.float64(largest * 2**bits)) <= MAX_FIXED:
            return bits
    return None


def pack_positions(means: np.ndarray, bits: int) -> np.ndarray:
    """[N, 3] -> [N, 9] bytes of 24-bit fixed point with ``bits`` fractional bits."""
    fixed = _round(means.astype(np.float64) * (1 << bits)).astype(np.int64)
    u = (fixed & 0xFFFFFF).astype(np.uint32)  # two's complement, 24 bits
    return np.stack([u & 0xFF, (u >> 8) & 0xFF, (u >> 16) & 0xFF], axis=-1).astype(np.uint8).reshape(len(means), 9)


def pack_quats_smallest_three(quats_xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] (x, y, z, w) -> [N, 4] bytes (the reference's ``packQuaternionSmallestThree``)."""
    q = quats_xyzw.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        others = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = np.minimum((511 * np.abs(q[:, i]) / math.sqrt(0.5) + 0.5).astype(np.uint32), 511)
        comp = np.where(others, (comp << 10) | (negbit << 9) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(len(q), 4)


def quantize_sh(sh_rest: np.ndarray) -> np.ndarray:
    """[N, K, 3] coefficients -> [N, K, 3] bytes, bucketed as the reference writer does."""
    q = (_round(sh_rest.astype(np.float32) * np.float32(128)) + 128).astype(np.int64)
    bucket = np.full(sh_rest.shape[1], SH_REST_BUCKET, np.int64)
    bucket[:3] = SH1_BUCKET
    bucket = bucket[None, :, None]
    q = np.trunc((q + bucket // 2) / bucket).astype(np.int64) * bucket  # C's truncating division
    return np.clip(q, 0, 255).astype(np.uint8)


def spz_bytes(gaussians: Gaussians) -> bytes:
    """The uncompressed SPZ payload (header and arrays) of ``gaussians`` (RDF coordinates)."""
    g = gaussians
    n, k = len(g), g.sh_rest.shape[1]
    means = g.means * FLIP_XYZ
    quats_xyzw = np.concatenate([g.quats[:, 1:] * FLIP_XYZ, g.quats[:, :1]], axis=1)
    sh_rest = g.sh_rest * FLIP_SH[:k, None]
    alphas = _to_uint8(255.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64))))
    bits = fractional_bits(means)
    header = struct.pack("<IIIBBBB", MAGIC, VERSION, n, g.sh_degree, bits, 0, 0)
    parts = [pack_positions(means, bits), alphas, _to_uint8(g.sh0 * (COLOR_SCALE * 255) + 127.5),
             _to_uint8((g.log_scales + 10.0) * 16.0), pack_quats_smallest_three(quats_xyzw), quantize_sh(sh_rest)]
    return header + b"".join(np.ascontiguousarray(p).tobytes() for p in parts)


def check_spz_range(gaussians: Gaussians) -> str | None:
    """Why ``gaussians`` do not fit SPZ, or None."""
    if fractional_bits(gaussians.means) is None:
        return f"positions beyond +-{MAX_FIXED} do not fit SPZ's 24-bit fixed point"
    return None


def write_spz(gaussians: Gaussians, f: BinaryIO) -> None:
    """Write ``gaussians`` as SPZ v3 (check :func:`check_spz_range` first)."""
    f.write(gzip.compress(spz_bytes(gaussians), compresslevel=6, mtime=0))
