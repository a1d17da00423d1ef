"""Keep glibc from returning memory to the OS after every large temporary.

Training allocates and frees the same multi-MB tensors every iteration; with glibc's default
thresholds each of them is a fresh mmap whose pages fault in again, which cost the torch paths
50-80% of their time on this project's 2-core reference machines. Raising
the mmap and trim thresholds makes freed blocks reusable. Opt out with SPLATK_NO_MALLOPT=1.
"""
from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

_done = False


def tune_malloc() -> bool:
    global _done
    if _done or os.environ.get("SPLATK_NO_MALLOPT") or not sys.platform.startswith("linux"):
        return False
    _done = True
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    ok = libc.mallopt(M_MMAP_THRESHOLD, 2**31 - 1)
    ok &= libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    ok &= libc.mallopt(M_TOP_PAD, 2**28)
    return bool(ok)
