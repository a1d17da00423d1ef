"""The torch device a command runs on, checked before any work starts.

`--device` takes any torch device string (cpu, cuda, cuda:1, mps...). A name torch does not know,
or a device this machine or this torch build lacks, is an :class:`InputError` rather than the
assertion torch raises deep inside the first tensor it tries to place there.
"""
from __future__ import annotations

import torch

from .errors import InputError


def resolve_device(name: str | torch.device, backend: str = "auto") -> torch.device:
    """``name`` as a torch device that works here; ``backend`` must be able to render on it."""
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise InputError(None, f"--device {str(name)!r}: not a torch device ({e})",
                         "use cpu, cuda, cuda:N or mps") from None
    try:
        torch.empty(0, device=dev)  # the one probe that covers every device type
    except (RuntimeError, AssertionError) as e:
        raise InputError(None, f"--device {str(name)!r}: not usable here: {e} (torch {torch.__version__})",
                         "use --device cpu") from None
    if dev.type != "cpu" and backend == "cpu":
        raise InputError(None, f"--device {str(name)!r}: backend 'cpu' (native) renders on the CPU only",
                         "use --backend torch or auto")
    return dev
