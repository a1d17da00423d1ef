"""Data-parallel training over processes (``torch.distributed``: gloo on CPU, NCCL on CUDA).

Every rank holds the whole model and draws the same B views per step (the view generator is
seeded alike everywhere); rank r renders views r, r + N, ... of them (:func:`my_share`). Each
rank's loss is its share of the batch mean plus 1/N of the regularisers, so the sum of the
ranks' gradients (:func:`World.sum_gradients`: one all-reduce over every per-primitive tensor
and every network parameter) is the gradient of the one-process batch. Whatever changes the
model's shape or draws randomness then runs on every rank from identical inputs: the summed
gradients, the summed loss (rollbacks), rank 0's clock (schedules, time budgets) and the
density-control generator seeded alike, so every rank makes the same decisions without a
message. Only rank 0 writes the run folder; a checkpoint is the whole state whatever the
number of ranks, so a run can resume with another number of processes.

A rank learns its place from the launcher's environment (``RANK``, ``WORLD_SIZE``,
``MASTER_ADDR``, ``MASTER_PORT``: torchrun's, or :func:`launch_local`'s for ``--nproc``). A
collective that fails (a peer died, or stayed silent for :data:`TIMEOUT_S`) raises
:class:`WorkerLost`.
"""
from __future__ import annotations

import os
import signal
import socket
import sys
import time
from dataclasses import dataclass
from datetime import timedelta
from typing import Callable, Sequence

import torch
import torch.distributed as dist

#: how long a rank waits at a collective for its peers before the job stops. Long enough for
#: rank 0's own work between two steps (writing a checkpoint, the initial test render of a
#: large scene); a peer that dies is noticed at once (its socket closes), this only bounds a
#: peer that hangs
TIMEOUT_S = 600.0
#: the launcher's environment variables a worker reads
ENV = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


class WorkerLost(RuntimeError):
    """Another rank of the job stopped (died, was killed, or timed out) mid-run."""


@dataclass(frozen=True)
class World:
    """This process's place in the job: ``rank`` of ``size`` (size 1: a one-process run, where
    every method below returns its input and sends nothing)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    # ---- collectives ---------------------------------------------------------------------------
    def sum_values(self, values: Sequence[float | torch.Tensor], device: torch.device) -> list[float]:
        """The sum over ranks of each value (losses, squared errors)."""
        if not self.distributed:
            return [float(v) for v in values]
        t = torch.stack([torch.as_tensor(v, dtype=torch.float64).detach().reshape(()).cpu() for v in values])
        t = t.to(_comm_device(device))
        _collective(dist.all_reduce, t)
        return t.cpu().tolist()

    def rank0_value(self, value: float, device: torch.device) -> float:
        """Rank 0's ``value`` on every rank (the step's duration: schedules follow one clock)."""
        if not self.distributed:
            return value
        t = torch.tensor([value], dtype=torch.float64, device=_comm_device(device))
        _collective(dist.broadcast, t, src=0)
        return float(t[0])

    def any(self, flag: bool, device: torch.device | None = None) -> bool:
        """True on every rank when ``flag`` is true on one (stop requests: Ctrl-C, SIGTERM)."""
        if not self.distributed:
            return flag
        t = torch.tensor([1.0 if flag else 0.0], device=_comm_device(device))
        _collective(dist.all_reduce, t)
        return bool(t[0] > 0)

    def sum_gradients(self, params: Sequence[torch.nn.Parameter]) -> int:
        """Replace every parameter's gradient by its sum over ranks, in one all-reduce; returns
        the bytes this rank sends into it. A parameter without a gradient anywhere keeps none
        (Adam then skips it, as in a one-process run)."""
        if not self.distributed or not params:
            return 0
        device = params[0].device
        has = torch.tensor([0.0 if p.grad is None else 1.0 for p in params], device=device)
        _collective(dist.all_reduce, has)
        live = [p for p, h in zip(params, has.tolist()) if h > 0]
        if not live:
            return 0
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in live])
        _collective(dist.all_reduce, flat)
        offset = 0
        for p in live:
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p).clone()
            offset += n
        return flat.numel() * flat.element_size()

    def observed(self, strategy, before: dict, n: int, device: torch.device) -> None:
        """After ``strategy.observe`` of this rank's views: its per-primitive statistics as if it
        had observed every rank's (``before``: :func:`statistics_before` of this step)."""
        names = strategy.statistics
        if not self.distributed or not names:
            return
        if not self.any(any(getattr(strategy, k) is not None for k in names), device):
            return
        for name, how in names.items():
            now = getattr(strategy, name)
            now = torch.zeros(n, device=device) if now is None else now
            if how == "sum":
                prev = before.get(name)
                base = prev if prev is not None and prev.shape == now.shape else torch.zeros_like(now)
                delta = now - base  # this rank's views' share; the sum over ranks is the batch's
                _collective(dist.all_reduce, delta)
                now = base + delta
            else:
                _collective(dist.all_reduce, now, op=dist.ReduceOp.MAX)
            setattr(strategy, name, now)

    def broadcast(self, obj=None):
        """Rank 0's ``obj`` (any picklable value: settings, a trainer's state) on every rank."""
        if not self.distributed:
            return obj
        box = [obj]
        _collective(dist.broadcast_object_list, box, src=0)
        return box[0]

    def gather(self, obj) -> list:
        """Every rank's ``obj``, in rank order, on every rank."""
        if not self.distributed:
            return [obj]
        out = [None] * self.size
        _collective(dist.all_gather_object, out, obj)
        return out


SINGLE = World()


def _comm_device(device: torch.device | None) -> torch.device:
    # NCCL moves CUDA tensors only; gloo takes CPU ones
    return device if device is not None and device.type == "cuda" else torch.device("cpu")


def _collective(fn: Callable, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except (RuntimeError, ValueError) as e:  # DistBackendError, DistNetworkError: a peer is gone
        raise WorkerLost(_short(e)) from None


def _short(e: Exception) -> str:
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return (lines[0] if lines else type(e).__name__)[:200]


def statistics_before(strategy) -> dict:
    """Copies of ``strategy``'s per-primitive statistics before a step's observations."""
    return {name: None if getattr(strategy, name) is None else getattr(strategy, name).clone()
            for name in strategy.statistics}


def my_share(views: Sequence[int], world: World) -> list[int]:
    """The views of one step this rank renders: r, r + N, ... of the step's B views."""
    return list(views[world.rank::world.size])


# ---- joining and leaving a job ----------------------------------------------------------------------
def launched_world() -> World:
    """This process's place as its launcher's environment says (SINGLE when not launched)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return SINGLE
    return World(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]), int(os.environ.get("LOCAL_RANK", "0")))


def join(world: World) -> None:
    """Join the launcher's process group (gloo for CPU tensors, NCCL for CUDA ones where CUDA
    is available); a rank that cannot reach rank 0 within TIMEOUT_S raises WorkerLost."""
    if not world.distributed or dist.is_initialized():
        return
    missing = [k for k in ENV if k not in os.environ]
    if missing:
        raise WorkerLost(f"the launcher's environment lacks {', '.join(missing)}")
    backend = "cpu:gloo,cuda:nccl" if torch.cuda.is_available() and dist.is_nccl_available() else "gloo"
    if torch.cuda.is_available():  # NCCL's object collectives use the current device: this rank's
        torch.cuda.set_device(world.local_rank % torch.cuda.device_count())
    try:
        dist.init_process_group(backend, timeout=timedelta(seconds=TIMEOUT_S))
    except (RuntimeError, ValueError) as e:
        raise WorkerLost(f"cannot join the job at {os.environ['MASTER_ADDR']}:{os.environ['MASTER_PORT']} "
                         f"({_short(e)})") from None


def leave() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def local_device(device: str, world: World) -> str:
    """``cuda`` on a rank of a job is the GPU of its local rank (one GPU per process)."""
    return f"cuda:{world.local_rank}" if device == "cuda" and world.distributed else device


# ---- the one-machine launcher (--nproc) ----------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: after a worker fails, how long the others get to notice it themselves (their next collective
#: fails at once when the peer is gone) before they are sent SIGTERM, and then SIGKILL
STOP_GRACE_S = 30.0


def launch_local(nproc: int, entrypoint: Callable, *args) -> dict[int, int]:
    """Run ``entrypoint(*args)`` in ``nproc`` worker processes on this machine (torch's
    multiprocessing, spawned, each with the environment torchrun would give it and a rendezvous
    on 127.0.0.1); returns {rank: exit code} of the workers that did not exit 0 (negative: killed
    by that signal).

    Ctrl-C reaches the workers from the terminal, and each stops at a step boundary as a
    one-process fit does; this process only waits for them. A SIGTERM sent to this process is
    passed on to them. When a worker fails, the others stop on their own when their next
    collective finds it gone; any still running STOP_GRACE_S later get SIGTERM, then SIGKILL.
    """
    import multiprocessing.connection

    import torch.multiprocessing as mp

    ctx = mp.start_processes(_rank_main, args=(nproc, free_port(), entrypoint, args), nprocs=nproc, join=False,
                             start_method="spawn")
    procs = ctx.processes

    def forward(signum, frame):
        for proc in procs:
            if proc.is_alive():
                os.kill(proc.pid, signum)

    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    old_term = signal.signal(signal.SIGTERM, forward)
    stopped = (0, 128 + signal.SIGINT, 128 + signal.SIGTERM)  # done, or stopped on request
    failed_at, sent = None, None
    try:
        while any(proc.is_alive() for proc in procs):
            multiprocessing.connection.wait([proc.sentinel for proc in procs if proc.is_alive()], timeout=1.0)
            if failed_at is None and any(proc.exitcode not in (None, *stopped) for proc in procs):
                failed_at = time.monotonic()
            if failed_at is not None and time.monotonic() - failed_at > STOP_GRACE_S:
                sent = signal.SIGKILL if sent is not None else signal.SIGTERM
                failed_at = time.monotonic()
                forward(sent, None)
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)
    for proc in procs:
        proc.join()
    return {rank: proc.exitcode for rank, proc in enumerate(procs) if proc.exitcode != 0}


def _rank_main(rank: int, nproc: int, port: int, entrypoint: Callable, args: tuple) -> None:
    os.environ.update({"RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": str(nproc),
                       "LOCAL_WORLD_SIZE": str(nproc), "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    try:
        entrypoint(*args)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    # The fit is written and the group left: end here, without the interpreter's teardown, where
    # a gloo thread still being destroyed can abort a finished worker ("terminate called
    # without an active exception") and turn its exit code into SIGABRT's.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
