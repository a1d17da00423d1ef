"""Output folders splatk owns: what ``--overwrite`` may replace, and one writer at a time.

The promises (``docs/reliability.md``):

* splatk replaces only folders it wrote itself. Every output folder it creates carries a marker
  file (:data:`MARKER`, JSON with the kind of output), and ``--overwrite`` empties a non-empty
  folder only when the marker names the kind being written: a run folder for ``fit``, a renders
  folder for ``export --format renders``, and so on. A folder without the marker (a scene, a
  photo folder, a home directory) is never emptied, whatever the flags.
* An output folder never is, or contains, an input (the scene, the photo), the current directory,
  the home directory or a filesystem root.
* Every check runs before anything is deleted or written (:func:`check_output_dir`).
* One writer per folder: :class:`OutputDir` holds a lock (``filelock``) while it writes; a
  second writer is refused with the process that holds it.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

from filelock import FileLock, Timeout

from . import __version__
from .errors import InputError

#: marker file in every output folder splatk creates
MARKER = ".splatk-output"
#: lock file held while a process writes the folder (filelock's; kept after release)
LOCK = ".splatk-lock"
#: who holds the lock (pid, host, command), written after taking it and removed on release;
#: separate from the lock file, which filelock truncates on every attempt to take it
OWNER = ".splatk-owner"
#: bookkeeping files that do not make a folder "not empty"
_BOOKKEEPING = frozenset({LOCK, OWNER})


def _resolved(path: Path) -> Path:
    return Path(os.path.abspath(Path(path).expanduser())).resolve()


def refuse_protected(out: Path, inputs: tuple | list = ()) -> None:
    """InputError when ``out`` is, or contains, an input, the current directory, the home
    directory or a filesystem root."""
    target = _resolved(out)
    if target == Path(target.anchor):
        raise InputError(out, "is a filesystem root", "choose a new folder for --out")
    protected = [(Path.cwd().resolve(), "the current directory"), (Path.home().resolve(), "your home directory")]
    protected += [(_resolved(p), f"the input {p}") for p in inputs if p is not None]
    for path, what in protected:
        if target == path or target in path.parents:
            relation = "is" if target == path else "contains"
            raise InputError(out, f"output folder {relation} {what}",
                             "choose a new folder for --out; splatk never writes into or deletes its inputs")


def read_marker(folder: Path) -> dict | None:
    """The marker of a folder splatk wrote, or None."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("kind"), str) else None


def write_marker(folder: Path, kind: str) -> None:
    """Mark ``folder`` as splatk's output of ``kind`` (what ``--overwrite`` may later replace)."""
    (Path(folder) / MARKER).write_text(json.dumps({"kind": kind, "splatk": __version__}) + "\n")


def lock_holder(folder: Path) -> str | None:
    """A description of the process writing ``folder``, or None when no process is."""
    lock_path = Path(folder) / LOCK
    if not lock_path.exists():
        return None
    lock = FileLock(lock_path)
    try:
        lock.acquire(timeout=0)
    except Timeout:
        return _owner_text(folder)
    except OSError:  # a read-only folder: nobody can be writing it through splatk
        return None
    lock.release()
    return None


def _owner_text(folder: Path) -> str:
    try:
        owner = json.loads((Path(folder) / OWNER).read_text())
        return f"pid {owner['pid']} on {owner['host']}, since {owner['since']}: {owner['command']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that has not yet said who it is"


def user_entries(folder: Path) -> list[Path]:
    return [p for p in Path(folder).iterdir() if p.name not in _BOOKKEEPING]


def check_output_dir(out: Path, kind: str, overwrite: bool, inputs: tuple | list = (),
                     locked: bool = False, resumable: bool = False) -> None:
    """Refuse, touching nothing, an output folder that cannot be written as ``kind``.

    Refused: a protected path (:func:`refuse_protected`); a file; a folder another process is
    writing; a non-empty folder without ``overwrite``; with ``overwrite``, a non-empty folder that
    splatk did not write as ``kind``; a folder that cannot be created or written. ``locked``:
    this process holds the folder's lock (the check is repeated under it). ``resumable``: the
    command has ``--resume``, so the fix names it.
    """
    out = Path(out)
    refuse_protected(out, inputs)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is a file, not a folder", "choose another --out")
    if out.is_dir():
        holder = None if locked else lock_holder(out)
        if holder:
            raise InputError(out, f"another splatk process is writing this folder ({holder})",
                             "wait for it to finish, or choose another --out")
        if user_entries(out):
            if not overwrite:
                resume = "--resume to continue a run, " if resumable else ""
                raise InputError(out, "output folder exists and is not empty",
                                 f"pass --overwrite to replace a splatk output, {resume}or choose another --out")
            marker = read_marker(out)
            if marker is None:
                raise InputError(out, f"--overwrite replaces only folders splatk wrote, and this one has no "
                                      f"{MARKER} marker", "choose another --out, or empty the folder yourself")
            if marker["kind"] != kind:
                raise InputError(out, f"holds a splatk {marker['kind']} output, not a {kind}",
                                 "choose another --out")
    probe = out
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(out, f"cannot create output folder: {probe} is not a folder", "choose a writable --out")
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as e:
        where = "output folder is not writable" if probe == out else f"cannot create output folder in {probe}"
        raise InputError(out, f"{where} ({e.strerror or e})", "choose a writable --out") from None


class OutputDir:
    """An output folder held for writing: created, locked, emptied when overwriting, marked.

    Use as a context manager around everything that writes the folder::

        check_output_dir(out, "run", overwrite, inputs=[scene])   # before any work
        ...                                                       # load and check inputs
        with OutputDir(out, "run", overwrite, inputs=[scene]):    # lock, empty, mark
            ...                                                   # write

    ``keep=True`` (resuming) takes the lock and keeps the contents.
    """

    def __init__(self, out: Path, kind: str, overwrite: bool = False, inputs: tuple | list = (),
                 keep: bool = False):
        self.path, self.kind, self.overwrite, self.inputs, self.keep = Path(out), kind, overwrite, inputs, keep
        self._lock: FileLock | None = None

    def __enter__(self) -> "OutputDir":
        out = self.path
        if not self.keep:
            check_output_dir(out, self.kind, self.overwrite, self.inputs)
        try:
            out.mkdir(parents=True, exist_ok=True)
            self._lock = FileLock(out / LOCK)
            try:
                self._lock.acquire(timeout=0)
            except Timeout:
                raise InputError(out, f"another splatk process is writing this folder ({_owner_text(out)})",
                                 "wait for it to finish, or choose another --out") from None
            (out / OWNER).write_text(json.dumps({
                "pid": os.getpid(), "host": socket.gethostname(),
                "since": time.strftime("%Y-%m-%d %H:%M:%S"), "command": " ".join(sys.argv)[:300]}))
            if not self.keep:
                # checked again under the lock: the folder may have changed since the first check
                check_output_dir(out, self.kind, self.overwrite, self.inputs, locked=True)
                for entry in user_entries(out):
                    if entry.is_dir() and not entry.is_symlink():
                        shutil.rmtree(entry)
                    else:
                        entry.unlink()
            if not self.keep or read_marker(out) is None:
                write_marker(out, self.kind)
        except OSError as e:
            self.__exit__(None, None, None)
            raise InputError(out, f"cannot write output folder ({e.strerror or e})", "choose a writable --out") from e
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self._lock is not None and self._lock.is_locked:
            (self.path / OWNER).unlink(missing_ok=True)
            self._lock.release()
        self._lock = None


def check_output_file(out: Path, overwrite: bool, inputs: tuple | list = ()) -> None:
    """Refuse an output file that exists (without ``overwrite``), that is a folder, or that is
    an input."""
    out = Path(out)
    target = _resolved(out)
    for p in inputs:
        if p is not None and _resolved(p) == target:
            raise InputError(out, "output file is an input", "choose another --out")
    if out.is_dir():
        raise InputError(out, "is a folder; this output is a file", "give a file name for --out")
    if out.exists() and not overwrite:
        raise InputError(out, "output file exists", "pass --overwrite or choose another --out")
