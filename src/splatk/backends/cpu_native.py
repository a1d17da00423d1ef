"""Native OpenMP CPU rasteriser: the ``cpu`` backend.

The C++ source in ``csrc/`` is compiled on first use (never at import) with
``torch.utils.cpp_extension.load`` into ``${SPLATK_CACHE_DIR:-~/.cache/splatk}/ext/<key>``, where
``<key>`` hashes the sources, the compiler flags, torch, Python and (for ``-march=native``) the
CPU, so editing a source rebuilds and a clean checkout builds itself. A file lock serialises
concurrent builds from several processes. If the build fails (no compiler, ...) the backend
reports itself unavailable, a single ``RuntimeWarning`` names the reason and ``auto`` falls back
to the ``torch`` backend.

Environment:
    SPLATK_CACHE_DIR: cache root (default ``~/.cache/splatk``).
    SPLATK_NATIVE_MARCH: ``0`` builds without ``-march=native`` (portable binary).
    SPLATK_BUILD_VERBOSE: ``1`` shows the compiler output.

Semantics and gradients are those of ``torch_ref.rasterize_torch`` (see ``splatk.backends``);
threads follow ``torch.get_num_threads()``.
"""
from __future__ import annotations

import hashlib
import os
import platform
import sys
import threading
import warnings
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from .types import PROFILE_KINDS, Profile, RasterOutput

_CSRC = Path(__file__).with_name("csrc")
_SOURCES = ("rasterize_cpu.cpp", "raster_kernels.cpp", "raster_kernels_f64.cpp", "ssim_ops.cpp",
            "project_ops.cpp", "sh_ops.cpp", "learned_ops.cpp", "planar_raster.cpp", "image_splat.cpp")
_HEADERS = ("raster_kernels.h", "raster_impl.h", "raster_common.h", "raster_binning.h", "raster_forward.h",
            "raster_backward.h", "fused_common.h", "simd.h", "bf16_mlp.h")
_KIND_CODES = {"gaussian": 0, "beta": 1, "student_t": 2, "table": 3}
assert set(_KIND_CODES) == set(PROFILE_KINDS)

_lock = threading.Lock()
_module = None
_error: str | None = None


def _flags() -> list[str]:
    # -ffp-contract=off: the kernels round like the torch reference (explicit FMAs only where
    # they accumulate), and the forward and backward passes see identical support masks.
    flags = ["-O3", "-fopenmp", "-fno-math-errno", "-ffp-contract=off", "-DNDEBUG"]
    if os.environ.get("SPLATK_NATIVE_MARCH", "1") != "0":
        flags.append("-march=native")
    return flags


def cache_dir() -> Path:
    """Root of splatk's on-disk cache (``SPLATK_CACHE_DIR`` or ``~/.cache/splatk``)."""
    root = os.environ.get("SPLATK_CACHE_DIR")
    return Path(root).expanduser() if root else Path.home() / ".cache" / "splatk"


def _cpu_signature() -> str:
    # -march=native binaries are CPU specific: a shared home on another machine rebuilds.
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith(("flags", "Features")):
                    return line
    except OSError:
        pass
    return platform.processor()


def _build_key(flags: list[str]) -> str:
    h = hashlib.sha256()
    for name in _SOURCES + _HEADERS:
        h.update(name.encode())
        h.update((_CSRC / name).read_bytes())
    h.update(" ".join(flags).encode())
    h.update(torch.__version__.encode())
    h.update(sys.implementation.cache_tag.encode())
    h.update(platform.machine().encode())
    h.update(os.environ.get("CXX", "").encode())
    if "-march=native" in flags:
        h.update(_cpu_signature().encode())
    return h.hexdigest()[:20]


class _FileLock:
    """Exclusive ``flock`` on a file; released by the kernel if the process dies."""

    def __init__(self, path: Path):
        self.path = path
        self.fh = None

    def __enter__(self):
        self.fh = open(self.path, "a+")
        try:
            import fcntl

            fcntl.flock(self.fh.fileno(), fcntl.LOCK_EX)
        except ImportError:  # not POSIX: builds are not serialised
            pass
        return self

    def __exit__(self, *exc):
        try:
            import fcntl

            fcntl.flock(self.fh.fileno(), fcntl.LOCK_UN)
        except ImportError:
            pass
        self.fh.close()


def _import_built(name: str, path: Path):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build():
    from torch.utils import cpp_extension

    flags = _flags()
    key = _build_key(flags)
    name = f"splatk_cpu_{key}"
    build_dir = cache_dir() / "ext" / key
    built = build_dir / f"{name}.so"
    done = build_dir / ".splatk-built"  # written after a complete build of this exact key
    if done.exists() and built.exists():
        try:  # the key covers sources, flags and torch: skip torch's ninja up-to-date check
            return _import_built(name, built)
        except ImportError:
            pass
    build_dir.mkdir(parents=True, exist_ok=True)
    with _FileLock(build_dir / ".splatk-build.lock"):
        # torch's own FileBaton ("lock") is only left behind by a build that died; we hold the
        # exclusive lock, so no other splatk build can be using it.
        baton = build_dir / "lock"
        if baton.exists():
            baton.unlink()
        module = cpp_extension.load(
            name=name,
            sources=[str(_CSRC / s) for s in _SOURCES],
            extra_cflags=flags,
            extra_ldflags=["-fopenmp"],
            extra_include_paths=[str(_CSRC)],
            build_directory=str(build_dir),
            verbose=os.environ.get("SPLATK_BUILD_VERBOSE") == "1",
        )
        done.write_text(f"{torch.__version__} {' '.join(flags)}\n")
        return module


def load_extension():
    """The compiled module, building it on first call; None (warned once) if it cannot build."""
    global _module, _error
    if _module is not None or _error is not None:
        return _module
    with _lock:
        if _module is None and _error is None:
            try:
                _module = _build()
            except Exception as exc:  # noqa: BLE001 - any build failure means "unavailable"
                lines = str(exc).strip().splitlines() or [type(exc).__name__]
                _error = f"{type(exc).__name__}: {lines[-1][:300]}"
                warnings.warn(
                    f"splatk: the native 'cpu' rasteriser could not be built ({_error}); "
                    "falling back to the slower 'torch' backend. Install a C++ compiler "
                    "(g++ >= 9) and ninja, or set SPLATK_BUILD_VERBOSE=1 to see the build log.",
                    RuntimeWarning,
                    stacklevel=3,
                )
    return _module


def available() -> bool:
    """Whether the native backend can run here (builds it on the first call)."""
    return load_extension() is not None


def unavailable_reason() -> str | None:
    """Why the build failed, or None."""
    return _error


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, params, background, depths, kind, width,
                height):
        ext = load_extension()
        threads = torch.get_num_threads()
        img, alpha, *state = ext.forward(
            means2d, conics, opacities, colors, depths, params, kind, width, height, background,
            threads,
        )
        ctx.save_for_backward(background, *state)
        ctx.meta = (means2d.shape[0], kind, width, height, colors.shape[1], params.shape[1])
        return img, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, v_img, v_alpha):
        background, *state = ctx.saved_tensors
        n, kind, width, height, channels, n_params = ctx.meta
        dtype = background.dtype
        v_img = v_img.to(dtype).contiguous()
        v_alpha = v_alpha.to(dtype).contiguous()
        v_means, v_conics, v_opac, v_colors, v_params, v_bg = load_extension().backward(
            state, n, kind, width, height, background, v_img, v_alpha, channels, n_params,
            torch.get_num_threads(),
        )
        return v_means, v_conics, v_opac, v_colors, v_params, v_bg, None, None, None, None


def rasterize_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    profile: Profile,
    width: int,
    height: int,
    background: torch.Tensor,
) -> RasterOutput:
    """Native rasteriser; same signature and semantics as ``torch_ref.rasterize_torch``.

    Args:
        means2d: [N, 2]; conics: [N, 3]; opacities: [N]; colors: [N, C]; depths: [N];
        profile: kind and params ([N, 1] beta / nu, [N, k] table); background: [C].
    Float32 or float64 (float64 when any float input is float64); CPU tensors only.
    """
    from ..errors import BackendUnavailable

    if load_extension() is None:
        raise BackendUnavailable(f"backend 'cpu' is not available here ({_error})")
    tensors = [means2d, conics, opacities, colors, background]
    if profile.params is not None:
        tensors.append(profile.params)
    if any(t.device.type != "cpu" for t in tensors + [depths]):
        raise ValueError("backend 'cpu' needs CPU tensors; use backend='auto' or 'torch'")
    dtype = torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32
    n = means2d.shape[0]
    kind = profile.kind
    if kind == "gaussian":
        params = means2d.new_zeros((n, 0), dtype=dtype)
    else:
        if profile.params is None:
            raise ValueError(f"profile {kind!r} needs params")
        params = profile.params
        if params.dim() != 2 or params.shape[0] != n:
            raise ValueError(f"profile params must be [N, n], got {tuple(params.shape)}")
        if kind in ("beta", "student_t") and params.shape[1] != 1:
            raise ValueError(f"profile {kind!r} needs params [N, 1], got {tuple(params.shape)}")
        if kind == "table" and params.shape[1] < 2:
            raise ValueError("table profile needs k >= 2 samples per primitive")

    def prep(t: torch.Tensor) -> torch.Tensor:
        return t.to(dtype).contiguous()

    depth_dtype = torch.float32 if depths.dtype == torch.float32 else torch.float64
    img, alpha = _RasterizeCPU.apply(
        prep(means2d),
        prep(conics),
        prep(opacities.reshape(-1)),
        prep(colors),
        prep(params),
        prep(background.reshape(-1)),
        depths.detach().reshape(-1).to(depth_dtype).contiguous(),
        _KIND_CODES[kind],
        int(width),
        int(height),
    )
    return RasterOutput(img, alpha)
