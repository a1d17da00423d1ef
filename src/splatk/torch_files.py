"""Reading the torch files splatk writes (models, checkpoints, kernel weights) without running code.

``torch.load`` unpickles, and a crafted pickle runs any code it names while it is read. Every file
splatk writes holds only tensors and plain values (dicts, lists, tuples, str, int, float, bool,
None), so every one is read with ``weights_only=True``: torch rebuilds those and refuses anything
else before building it. A refused file is an :class:`~splatk.errors.InputError`; it is never read
a second time without the restriction. Run folders and model files can then be shared as freely
as images.
"""
from __future__ import annotations

import pickle
import warnings
from pathlib import Path

import torch

from .errors import InputError

#: what the refusal says: where such a file comes from, and why it is not read
REFUSED = ("holds Python objects besides tensors and plain values, so it was not loaded (loading it "
           "could run code): written by an older splatk or not a splatk file")


def load_torch_file(path: str | Path, fix: str, map_location: str | torch.device = "cpu"):
    """``torch.load(path, weights_only=True)``.

    Args:
        path: the file.
        fix: how to get a good file, for the error (e.g. "re-run `splatk fit`").
        map_location: where tensors go.

    Raises:
        InputError: the file holds an object other than tensors and plain values.
        Exception: whatever torch raises for a missing, truncated or non-torch file (the caller
            words that error for its kind of file).
    """
    try:
        with warnings.catch_warnings():
            # torch warns about pickle protocols it did not write; the file is read or refused
            # all the same, and a refusal is our one-line error
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        # torch names the refused class or function as "GLOBAL module.name"; other unpickling
        # errors (an unknown opcode in random bytes) are corrupt files, left to the caller
        if "GLOBAL" not in str(e):
            raise
        raise InputError(path, REFUSED, fix) from None
