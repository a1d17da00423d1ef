"""Progress displays for long commands: a live rich bar on a terminal, plain lines otherwise.

When stderr is a log file, a pipe, a batch job or CI, a live bar prints nothing until it stops;
:class:`PlainProgress` prints one line of the same fields every few seconds instead. Both take
the same calls (``start``, ``add_task``, ``update``, ``stop``), so commands do not branch on it.
"""
from __future__ import annotations

import time
from typing import Callable

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)

#: seconds between two plain progress lines unless a command's --log-every says otherwise
DEFAULT_LOG_EVERY = 10.0


class PlainProgress:
    """One plain line of progress every ``every`` seconds (and one at the end), for logs.

    A line reads ``NAME IT/TOTAL (P%)  FIELDS  R it/s  elapsed H:MM:SS  ETA H:MM:SS``; ``fields`` is
    a format string over the fields passed to ``add_task`` / ``update`` (e.g. ``"loss {loss:.4f}"``).
    The rate counts the steps since ``add_task``, so a resumed run's ETA is about this process.
    """

    def __init__(self, console: Console, fields: str, every: float = DEFAULT_LOG_EVERY,
                 clock: Callable[[], float] = time.monotonic):
        self.console, self.fields, self.every, self.clock = console, fields, every, clock
        self._tasks: dict[int, dict] = {}

    def start(self) -> None:
        pass

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields) -> int:
        task_id = len(self._tasks)
        now = self.clock()
        self._tasks[task_id] = {"name": description, "total": total, "completed": completed, "fields": fields,
                                "t0": now, "start": completed, "printed_at": now, "printed": completed}
        return task_id

    def update(self, task_id: int, completed: float | None = None, total: float | None = None, **fields) -> None:
        task = self._tasks[task_id]
        if completed is not None:
            task["completed"] = completed
        if total is not None:
            task["total"] = total
        task["fields"].update(fields)
        if self.clock() - task["printed_at"] >= self.every:
            self._print(task)

    def stop(self) -> None:
        for task in self._tasks.values():
            if task["completed"] != task["printed"]:
                self._print(task)

    def _print(self, task: dict) -> None:
        now = self.clock()
        done, total = task["completed"], task["total"]
        elapsed = now - task["t0"]
        rate = (done - task["start"]) / elapsed if elapsed > 0 else 0.0
        share = f" ({100 * done / total:.0f}%)" if total else ""
        eta = _clock_time((total - done) / rate) if total and rate > 0 else "?"
        parts = [f"{task['name']} {int(done)}/{int(total) if total else '?'}{share}",
                 self.fields.format(**task["fields"]), f"{rate:.1f} it/s", f"elapsed {_clock_time(elapsed)}",
                 f"ETA {eta}"]
        line = "  ".join(p for p in parts if p)
        # written, not console.print: rich would wrap the line at its guess of a width
        print(line, file=self.console.file, flush=True)
        task["printed_at"], task["printed"] = now, done


def stderr_console() -> Console:
    """The console for a command's messages and progress; in a log, long lines stay whole (rich
    would wrap them at 80 columns there)."""
    console = Console(stderr=True)
    if not console.is_terminal:
        console.soft_wrap = True
    return console


def _clock_time(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def training_progress(console: Console | None = None, log_every: float = DEFAULT_LOG_EVERY) -> Progress | PlainProgress:
    """`splatk fit`'s display; fields ``loss``, ``psnr``, ``num`` (primitives) and ``rate`` (it/s)."""
    console = console or Console(stderr=True)
    if not console.is_terminal:
        return PlainProgress(console, "loss {loss:.4f}  PSNR {psnr:.2f}  {num:,} prims", every=log_every)
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.4f}"),
        TextColumn("PSNR {task.fields[psnr]:5.2f}"),
        TextColumn("{task.fields[num]:>7,} prims"),
        TextColumn("{task.fields[rate]:5.1f} it/s"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


def image_progress(console: Console, kernel: str, log_every: float = DEFAULT_LOG_EVERY) -> Progress | PlainProgress:
    """`splatk image`'s display; fields ``loss`` and ``psnr``."""
    if not console.is_terminal:
        return PlainProgress(console, "loss {loss:.5f}  PSNR {psnr:.2f}", every=log_every)
    return Progress(
        TextColumn(f"[bold]image {kernel}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.5f}"), TextColumn("PSNR {task.fields[psnr]:5.2f}"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )


def frames_progress(console: Console, log_every: float = DEFAULT_LOG_EVERY) -> Progress | PlainProgress:
    """`splatk render`'s display: frames rendered of the video's."""
    if not console.is_terminal:
        return PlainProgress(console, "", every=log_every)
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )


def pretrain_progress(console: Console, target: str, log_every: float = DEFAULT_LOG_EVERY) -> Progress | PlainProgress:
    """`splatk pretrain`'s display; fields ``target`` and ``loss``."""
    if not console.is_terminal:
        return PlainProgress(console, "{target}  loss {loss:.4f}", every=log_every)
    return Progress(
        TextColumn("[bold]pretrain {task.fields[target]}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.4f}"), TimeElapsedColumn(), console=console,
    )
