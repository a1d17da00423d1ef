"""Errors a user can act on.

Every problem with user input is raised as :class:`InputError` naming the file and the fix.
The CLI turns it into a one-line message and exit code 2 (full traceback only with ``-v``).
"""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: names the offending path, what is wrong and how to fix it."""

    def __init__(self, path: str | Path | None, problem: str, fix: str | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.fix = fix
        super().__init__(self.message())

    def message(self) -> str:
        where = f"{self.path}: " if self.path is not None else ""
        tail = f" ({self.fix})" if self.fix else ""
        return f"{where}{self.problem}{tail}"


class BackendUnavailable(RuntimeError):
    """A rasteriser backend cannot run here (e.g. no compiler for the native CPU backend)."""
