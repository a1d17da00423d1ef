"""What machine a result came from, recorded next to every bench figure.

Training amplifies rounding differences: the same run (seed, code, settings) is bit-identical on
one machine, across thread counts too, yet moves between CPUs ("Reading these figures" in
docs/results.md). The native backend builds with ``-march=native`` and torch picks its vector
kernels by CPU capability, so a figure is only comparable with one from the same CPU features;
this says which.
"""
from __future__ import annotations

import os
import platform

import torch

from . import __version__

#: the CPU features that change which code runs (native build and torch's kernel dispatch)
CPU_FEATURES = ("avx2", "fma", "avx512f", "avx512_bf16", "amx_tile", "asimd", "sve")


def _cpuinfo() -> tuple[str, set[str]]:
    model, flags = platform.processor() or platform.machine(), set()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name" and value.strip():
                    model = value.strip()
                elif key in ("flags", "Features") and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    return model, flags


def machine_info() -> dict:
    model, flags = _cpuinfo()
    try:
        capability = torch.backends.cpu.get_cpu_capability()
    except AttributeError:  # older torch
        capability = None
    return {
        "cpu": model,
        "cpu_features": [f for f in CPU_FEATURES if f in flags],
        "logical_cpus": os.cpu_count(),
        "torch": torch.__version__,
        "torch_cpu_capability": capability,
        "splatk": __version__,
        "native_march": os.environ.get("SPLATK_NATIVE_MARCH", "1") != "0",
    }


def memory_bytes() -> int:
    """This machine's physical memory in bytes (or a cgroup's limit when lower)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:  # containers: cgroup v2's limit
        limit = open("/sys/fs/cgroup/memory.max").read().strip()
        if limit.isdigit():
            total = min(total, int(limit))
    except OSError:
        pass
    return total
