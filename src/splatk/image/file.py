"""The file `splatk image` writes: the fitted 2D splats, byte for byte what the budget paid for.

``splats.bin`` is a 20-byte header and then exactly ``Splats2D.describe_bytes()["bytes"]`` of
payload, so the size a run reports can be checked with ``ls -l``, and the image the run measured
is the image this file redraws (:func:`load_splats2d`, ``splatk image-decode``). Little-endian:

    header   magic "SPLK2D", version u8, kernel u8 (0 gaussian, 1 gabor, 2 learned, 3 learned-paper,
             4 gabsplat), n u32,
             height u16, width u16, grid u8, latent_dim u8, palette entries u16 (0: none)
    per splat, column by column (the parameters as trained, so a reload is exact):
             xy_raw [n, 2] f32, chol [n, 3] f32 (gabsplat: sigmas [n, 2] f32, angle [n] f32),
             colors [n, 3] f32
             gabor:   amplitudes [n, 2, K] f32, frequencies [n, 2, K] f32
             gabsplat: the top K coefficients [n, 2, K] f32, their bank indices [n, 2, K] u8
             learned-paper: latents [n, L] f32
             learned: turn [n] u8 (steps of 2 pi / 256), then palette index [n] u8 with a
                      palette, else latents [n, L] f32
    shared   learned, learned-paper: decoder weights and biases (layer 1, 2, 3) f16;
             learned: palette [K, L] f16
"""
from __future__ import annotations

import math
import os
import struct
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..models.io import atomic_write
from .bytes import MAX_SHAPES, SHARED_DTYPE, bytes_per_primitive, network_bytes
from .kernels import GABOR_WAVES, GABSPLAT_BANK, GABSPLAT_TOP, KERNELS, TURN_STEPS, GabSplatKernel2D, image_kernel
from .model import Splats2D

MAGIC = b"SPLK2D"
VERSION = 1
_HEADER = struct.Struct("<6sBBIHHBBH")
HEADER_BYTES = _HEADER.size
#: the largest image a file may declare: decoding draws [H, W, 3] float32 (64 Mpx: 768 MiB), so a
#: 20-byte header cannot ask for the 51 GB of a 65535 x 65535 image
MAX_PIXELS = 1 << 26
#: the largest learned-kernel table (nodes per axis) a file may declare: decoding makes [N, G, G]
#: floats, and 4 to 8 nodes are what fits use
MAX_GRID = 32
_F32, _F16, _U8 = np.dtype("<f4"), np.dtype("<f2"), np.dtype("u1")
assert SHARED_DTYPE == torch.float16  # the shared block below is written as f16


def _decoder_tensors(model: Splats2D) -> list[torch.Tensor]:
    d = model.decoder
    return [d.l1.weight, d.l1.bias, d.l2.weight, d.l2.bias, d.l3.weight, d.l3.bias]


def encode_splats2d(model: Splats2D) -> bytes:
    """The file's bytes for ``model`` (a learned model's shared part must already be float16-exact:
    :meth:`Splats2D.round_shared`, which the fit calls)."""
    if (max(model.height, model.width) > 0xFFFF or model.height * model.width > MAX_PIXELS
            or (model.kernel2d.decoded and model.grid > MAX_GRID) or model.latent_dim > 0xFF):
        raise ValueError(f"image size (at most {MAX_PIXELS} pixels), grid (at most {MAX_GRID}) or latent "
                         "size too large for the splat file")
    palette = model.palette if model.kernel == "learned" and model.palette is not None else None
    header = _HEADER.pack(MAGIC, VERSION, KERNELS.index(model.kernel), model.n, model.height, model.width,
                          model.grid, model.latent_dim if model.kernel2d.decoded else 0,
                          0 if palette is None else palette.shape[0])

    def f32(t):
        return t.detach().cpu().numpy().astype(_F32).tobytes()

    if model.kernel == "gabsplat":
        parts = [header, f32(model.xy_raw), f32(model.sigmas), f32(model.angle), f32(model.colors)]
        top = GabSplatKernel2D.top(model)
        parts += [f32(model.wave_coeffs.gather(2, top)), top.cpu().to(torch.uint8).numpy().tobytes()]
    else:
        parts = [header, f32(model.xy_raw), f32(model.chol), f32(model.colors)]
    if model.kernel == "gabor":
        parts += [f32(model.gabor_amps), f32(model.gabor_freqs)]
    if model.kernel == "learned":
        parts.append(model.turn_steps().cpu().to(torch.uint8).numpy().tobytes())
        parts.append(model.shape_index.cpu().to(torch.uint8).numpy().tobytes() if palette is not None
                     else f32(model.latents))
    if model.kernel == "learned-paper":
        parts.append(f32(model.latents))
    if model.kernel2d.decoded:
        shared = _decoder_tensors(model) + ([palette] if palette is not None else [])
        for t in shared:
            half = t.detach().cpu().to(SHARED_DTYPE)
            if not torch.equal(half.float(), t.detach().cpu().float()):
                raise ValueError("the learned kernel's decoder and palette must be rounded to float16 first "
                                 "(Splats2D.round_shared)")
            parts.append(half.numpy().astype(_F16).tobytes())
    return b"".join(parts)


def _repeats(top: torch.Tensor) -> bool:
    """Whether an axis names one bank index twice ([n, 2, K]): the coefficients would collide."""
    srt = top.sort(2).values
    return bool((srt[..., 1:] == srt[..., :-1]).any())


def save_splats2d(model: Splats2D, path: str | Path) -> Path:
    """Write :func:`encode_splats2d` to ``path`` atomically (temp file, fsync, rename)."""
    data = encode_splats2d(model)
    return atomic_write(path, lambda f: f.write(data))


class _Reader:
    """Reads consecutive arrays from the payload; a short file is an InputError naming it."""

    def __init__(self, data: bytes, path: Path):
        self.data, self.pos, self.path = data, HEADER_BYTES, path

    def take(self, dtype: np.dtype, shape: tuple[int, ...]) -> torch.Tensor:
        count = int(np.prod(shape))
        end = self.pos + count * dtype.itemsize
        if end > len(self.data):
            raise InputError(self.path, f"splat file is truncated ({len(self.data)} bytes, needs at least {end})",
                             "re-run `splatk image` to write it again")
        arr = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos).reshape(shape)
        self.pos = end
        return torch.from_numpy(arr.astype(np.float32 if dtype.kind == "f" else np.int64))


def payload_bytes(kernel: str, n: int, latent_dim: int, entries: int) -> int:
    """Bytes after the header of a file holding ``n`` splats (``Splats2D.describe_bytes()["bytes"]``)."""
    return bytes_per_primitive(kernel, latent_dim, entries) * n + network_bytes(kernel, latent_dim, entries)


def _check_header(path: Path, kernel: str, n: int, height: int, width: int, grid: int, latent_dim: int,
                  entries: int, file_bytes: int) -> None:
    """Refuse a header whose sizes the file does not hold, or whose decoding would allocate more
    than :data:`MAX_PIXELS` / :data:`MAX_GRID` allow, before anything is allocated: the header's
    counts are only claims until the file's length backs them."""
    corrupt = "splat file header is corrupt"
    again = "re-run `splatk image` to write it again"
    if height * width > MAX_PIXELS:
        raise InputError(path, f"{corrupt} (a {width}x{height} image, over the {MAX_PIXELS} pixel limit)", again)
    decoded = image_kernel(kernel).decoded
    if (not decoded and latent_dim) or (kernel != "learned" and entries):
        raise InputError(path, f"{corrupt} (latents or a palette for the {kernel} kernel)", again)
    if decoded and (grid > MAX_GRID or entries > MAX_SHAPES):
        raise InputError(path, f"{corrupt} (table grid {grid} or palette of {entries} past the limits "
                               f"{MAX_GRID} and {MAX_SHAPES})", again)
    expected = HEADER_BYTES + payload_bytes(kernel, n, latent_dim, entries)
    if file_bytes < expected:
        raise InputError(path, f"splat file is truncated or its header is corrupt ({file_bytes} bytes, "
                               f"the header declares {expected})", again)
    if file_bytes > expected:
        raise InputError(path, f"splat file has {file_bytes - expected} bytes past its end (corrupt or not ours)")


def load_splats2d(path: str | Path) -> Splats2D:
    """The :class:`Splats2D` stored in ``path`` (float32 tensors on the CPU).

    The header's sizes are checked against the file's length (and :data:`MAX_PIXELS`,
    :data:`MAX_GRID`) before the payload is read or the model allocated.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "splat file not found", "pass the splats.bin that `splatk image` wrote")
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
        if len(head) < HEADER_BYTES or head[:len(MAGIC)] != MAGIC:
            raise InputError(path, "not a splatk image splat file (bad header)",
                             "pass the splats.bin that `splatk image` wrote")
        _, version, kind, n, height, width, grid, latent_dim, entries = _HEADER.unpack(head)
        if version != VERSION:
            raise InputError(path, f"splat file version {version} is not supported (this splatk reads {VERSION})")
        if kind >= len(KERNELS) or n < 1 or height < 1 or width < 1:
            raise InputError(path, "splat file header is corrupt (kernel, count or size out of range)")
        kernel = KERNELS[kind]
        _check_header(path, kernel, n, height, width, grid, latent_dim, entries, os.fstat(f.fileno()).st_size)
        data = head + f.read()
    model = Splats2D(kernel, n, height, width, grid=max(grid, 1), latent_dim=latent_dim, shapes=entries)
    r = _Reader(data, path)
    with torch.no_grad():
        model.xy_raw.copy_(r.take(_F32, (n, 2)))
        if kernel == "gabsplat":
            model.sigmas.copy_(r.take(_F32, (n, 2)))
            model.angle.copy_(r.take(_F32, (n,)))
        else:
            model.chol.copy_(r.take(_F32, (n, 3)))
        model.colors.copy_(r.take(_F32, (n, 3)))
        if kernel == "gabsplat":
            coeffs = r.take(_F32, (n, 2, GABSPLAT_TOP))
            top = r.take(_U8, (n, 2, GABSPLAT_TOP))
            if int(top.max()) >= GABSPLAT_BANK or _repeats(top):
                raise InputError(path, "splat file is corrupt (a wave index past the bank or repeated)")
            model.wave_coeffs.zero_()
            model.wave_coeffs.scatter_(2, top, coeffs)
        if kernel == "gabor":
            model.gabor_amps.copy_(r.take(_F32, (n, 2, GABOR_WAVES)))
            model.gabor_freqs.copy_(r.take(_F32, (n, 2, GABOR_WAVES)))
        if kernel == "learned":
            model.turn.copy_(r.take(_U8, (n,)).float() * (2.0 * math.pi / TURN_STEPS))
            if entries:
                index = r.take(_U8, (n,))
            else:
                model.latents.copy_(r.take(_F32, (n, latent_dim)))
        if kernel == "learned-paper":
            model.latents.copy_(r.take(_F32, (n, latent_dim)))
        if model.kernel2d.decoded:
            for t in _decoder_tensors(model):
                t.copy_(r.take(_F16, tuple(t.shape)))
            if entries:
                palette = r.take(_F16, (entries, latent_dim))
                if int(index.max()) >= entries:
                    raise InputError(path, "splat file is corrupt (a palette index past the palette)")
                model.palette = torch.nn.Parameter(palette)
                model.shape_index = index
    if r.pos != len(data):  # the sizes above and payload_bytes disagree: a bug, not a bad file
        raise AssertionError(f"{path}: read {r.pos} of {len(data)} bytes")
    return model
