"""A fit on several processes (``--nproc N``, torchrun): the settings rules, and the start that
makes every rank begin from rank 0's state.

Rank 0 runs the fit as one process would (checks, run folder, initial render) and then sends
its start to the other ranks: the scene path, the settings and the trainer's whole state
(:meth:`Trainer.state_dict`), or its one-line error. Each other rank checks its own settings
and scene against rank 0's, loads the state and trains beside it; a problem on any rank is
then an input error on every rank. The training itself is :mod:`splatk.train.distributed`'s.
"""
from __future__ import annotations

from ..errors import InputError
from ..option_rules import int_range, option_error, valid
from ..train.distributed import World, launched_world

#: settings that may differ between the ranks of one job: each machine's own
PER_MACHINE = ("threads", "device", "train.device")


def process_options(opts: dict, sources: dict, new_run: bool) -> None:
    """``nproc`` from a launcher's environment (torchrun) when this process is one of its
    workers; a new run's ``batch_views`` defaults to ``nproc`` (one view per process and step)."""
    world = launched_world()
    if world.distributed:
        if opts.get("nproc") not in (None, world.size):
            raise option_error("nproc", opts["nproc"], f"this process is one of {world.size} that its launcher "
                               "started", "drop --nproc under torchrun: the launcher sets the processes",
                               sources.get("nproc"))
        opts["nproc"] = world.size
        sources["nproc"] = "launcher's WORLD_SIZE"
    if new_run and "nproc" in opts and "batch_views" not in opts and valid(opts["nproc"], int_range(1, 256)):
        opts["batch_views"] = opts["nproc"]
        sources["batch_views"] = "default for --nproc: one view per process"


def check_processes(cfg, sources: dict) -> None:
    """A data-parallel run gives every process at least one view per step; --budget auto's
    selection runs in one process."""
    if cfg.nproc > cfg.train.batch_views:
        raise option_error("nproc", cfg.nproc, f"more processes than views per step (--batch-views "
                           f"{cfg.train.batch_views})", f"give --batch-views {cfg.nproc} or more, or fewer processes",
                           sources.get("nproc"))
    if cfg.auto_budget is not None:
        raise option_error("nproc", cfg.nproc, "several processes train with a fixed --budget",
                           "use --nproc 1 with --budget auto, or give a number", sources.get("nproc"))


class Start:
    """Rank 0's side: send the start once, or the error that stopped it before the start."""

    def __init__(self, world: World):
        self.world, self.sent = world, False
        #: the settings as checked, before the fit resolves any (``init: auto`` -> sfm or random),
        #: which is how every other rank has them
        self.settings: dict | None = None

    def send(self, scene_path, fingerprint: str, state: dict) -> None:
        """Send rank 0's start; InputError on every rank when another rank found a problem."""
        self.sent = True
        self.world.broadcast({"scene": str(scene_path), "settings": self.settings, "fingerprint": fingerprint,
                              "state": state})
        agree(self.world, None)

    def fail(self, message: str) -> None:
        if self.world.distributed and not self.sent:
            self.sent = True
            self.world.broadcast({"error": message})


def receive(world: World) -> dict:
    """The other ranks' side: rank 0's start; rank 0's error as an InputError."""
    start = world.broadcast(None)
    if "error" in start:
        raise InputError(None, f"rank 0 stopped: {start['error']}")
    return start


def agree(world: World, problem: str | None) -> None:
    """Every rank's problem with the start (None: none); InputError on every rank if one has."""
    problems = [(rank, p) for rank, p in enumerate(world.gather(problem)) if p]
    if problems:
        rank, p = problems[0]
        raise InputError(None, p,
                         "start every process with the same command, scene and files")


def settings_mismatch(mine: dict, rank0: dict, rank: int) -> str | None:
    """The first setting (dotted name) of rank ``rank`` whose value differs from rank 0's, as a
    message."""
    a, b = _flatten(mine), _flatten(rank0)
    for key in sorted(set(a) | set(b)):
        if key not in PER_MACHINE and a.get(key) != b.get(key):
            return f"setting {key} is {a.get(key)!r} on rank {rank} but {b.get(key)!r} on rank 0"
    return None


def _flatten(d: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in d.items():
        if isinstance(v, dict) and k not in ("background", "kernel_options"):
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat
