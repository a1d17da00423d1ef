"""Errors a user can act on.

Every problem with user input is raised as :class:`InputError` naming the file and the fix.
The CLI turns it into a one-line message and exit code 2 (full traceback only with ``-v``).
"""
from __future__ import annotations

import re
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
        # One line whatever the problem's text holds (parsers' messages quote the input over
        # several lines): scripts read the first line of stderr. Only line breaks are replaced,
        # so a path's own spacing stays as it is.
        return re.sub(r"[ \t]*[\r\n]+[ \t]*", " ", f"{where}{self.problem}{tail}")


class BackendUnavailable(RuntimeError):
    """A rasteriser backend cannot run here (e.g. no compiler for the native CPU backend)."""


class TrainingStalled(RuntimeError):
    """Training cannot get past a point: rollbacks to the same healthy state keep failing.

    The CLI prints it in one line and exits with code 3; the run folder keeps the last healthy
    state as its checkpoint.
    """

    def __init__(self, reason: str, cause: str, run: Path | None = None):
        self.reason, self.cause, self.run = reason, cause, run
        super().__init__(self.message())

    def at(self, run: str | Path) -> "TrainingStalled":
        return TrainingStalled(self.reason, self.cause, Path(run))

    def message(self) -> str:
        where = f"{self.run}: " if self.run is not None else ""
        kept = (f"; the last healthy state is in {self.run / 'checkpoints' / 'last.pt'}"
                if self.run is not None else "")
        return f"{where}training stalled: {self.reason} (likely cause: {self.cause}{kept})"
