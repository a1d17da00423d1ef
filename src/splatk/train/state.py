"""A trainer's whole state as a dict of plain values and tensors, and back.

Checkpoints (``torch.save``, loaded with ``weights_only=True``), ``--resume`` and the guard's
rollback snapshots all use it: parameters, Adam moments, RNGs (torch, numpy, Python, the view
and MCMC generators, CUDA's where it draws), the view queue, the loss statistics, the step-size
cut, the clock and the event log. Restoring it continues bit for bit where it was taken.
"""
from __future__ import annotations

import copy
import random
from dataclasses import asdict

import numpy as np
import torch
from torch import nn


def numpy_rng_state() -> tuple:
    """``np.random.get_state()`` with its key array as an int64 tensor."""
    name, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    return name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached_gaussian)


def set_numpy_rng_state(state) -> None:
    name, keys, pos, has_gauss, cached_gaussian = state
    np.random.set_state((name, keys.cpu().numpy().astype(np.uint32), pos, has_gauss, cached_gaussian))


def trainer_state(tr) -> dict:
    g = tr.guard
    return {
        "it": tr.it,
        "elapsed": tr.elapsed,
        "lr_scale": tr.lr_scale,
        "events": list(tr.events),
        "loss_mean": (g.loss_mean, g.best_loss_mean, g.steps_since_reset, g.start_loss_mean),
        "prims": {k: v.detach().clone() for k, v in tr.model.prims.items()},
        "kernel": copy.deepcopy(tr.model.kernel.state_dict()),
        "opt": copy.deepcopy(tr.opt.state_dict()),
        "net_opt": copy.deepcopy(tr.net_opt.state_dict()) if tr.net_opt else None,
        "view_gen": tr.view_gen.get_state(),
        "mcmc_gen": tr.mcmc_gen.get_state(),
        "view_queue": list(tr.view_queue),
        "strategy": tr.strategy.state_dict(),
        "torch_rng": torch.get_rng_state(),
        # plain values and tensors only, so that checkpoints load with weights_only=True
        # (numpy's state holds an array: its 624 uint32 keys go in an int64 tensor)
        "numpy_rng": numpy_rng_state(),
        "python_rng": random.getstate(),  # (version, tuple of ints, float or None)
        # draws on a GPU without a generator of ours (torch's default one there)
        "cuda_rng": torch.cuda.get_rng_state(tr.device) if tr.device.type == "cuda" else None,
        "config": asdict(tr.cfg),
    }


def load_trainer_state(tr, sd: dict) -> None:
    tr.it = sd["it"]
    tr.elapsed = sd["elapsed"]
    tr.lr_scale = sd.get("lr_scale", 1.0)
    tr.events = list(sd.get("events", []))
    # checkpoints before the start-loss check hold three values; theirs starts afresh
    mean, best, steps, start = (tuple(sd.get("loss_mean", (None, None, 0))) + (None,))[:4]
    g = tr.guard
    g.loss_mean, g.best_loss_mean, g.steps_since_reset, g.start_loss_mean = mean, best, steps, start
    tr.model.prims = nn.ParameterDict(
        {k: nn.Parameter(v.clone().to(tr.device)) for k, v in sd["prims"].items()}
    )
    tr.model.kernel.load_state_dict(sd["kernel"])
    tr.strategy.load_state_dict({k: v.to(tr.device) for k, v in (sd.get("strategy") or {}).items()})
    tr.build_optimizers()
    # deep copy: Optimizer.load_state_dict keeps the given tensors, and Adam updates its
    # moments and step counts in place, which would rewrite a rollback snapshot
    tr.opt.load_state_dict(copy.deepcopy(sd["opt"]))
    if tr.net_opt is not None and sd.get("net_opt") is not None:
        tr.net_opt.load_state_dict(_regrouped(copy.deepcopy(sd["net_opt"]), tr.net_opt))
    # generator states are CPU byte tensors whatever the device
    tr.view_gen.set_state(sd["view_gen"].cpu())
    mcmc_state = sd["mcmc_gen"].cpu()
    if mcmc_state.numel() == tr.mcmc_gen.get_state().numel():
        tr.mcmc_gen.set_state(mcmc_state)
    else:
        # the run moved between a CPU and a GPU, whose generators keep states of other kinds:
        # MCMC's draws go on from a stream that the run's seed and this iteration fix
        tr.mcmc_gen.manual_seed(tr.cfg.seed + 1 + tr.it)
        tr.events.append({"iteration": tr.it, "event": "device_changed", "message":
                          f"iteration {tr.it}: the run continues on {tr.device.type}, whose generator keeps "
                          "another kind of state: MCMC's random draws go on from a new stream (seed + iteration)"})
    tr.view_queue = list(sd["view_queue"])
    torch.set_rng_state(sd["torch_rng"].cpu())
    if sd.get("cuda_rng") is not None and tr.device.type == "cuda":
        torch.cuda.set_rng_state(sd["cuda_rng"].cpu(), tr.device)
    set_numpy_rng_state(sd["numpy_rng"])
    version, internal, gauss_next = sd["python_rng"]
    random.setstate((version, tuple(internal), gauss_next))


def _regrouped(saved: dict, opt: torch.optim.Optimizer) -> dict:
    """A network optimiser's state saved with one parameter group (checkpoints written before
    the learned kernel gave each network its own group) split into ``opt``'s groups. The
    parameters keep their order, so their moments carry over unchanged."""
    if len(saved["param_groups"]) == len(opt.param_groups):
        return saved
    ids = [i for g in saved["param_groups"] for i in g["params"]]
    hyper = {k: v for k, v in saved["param_groups"][0].items() if k != "params"}
    groups, start = [], 0
    for g in opt.param_groups:
        groups.append({**hyper, "lr_mult": g["lr_mult"], "params": ids[start:start + len(g["params"])]})
        start += len(g["params"])
    return {"state": saved["state"], "param_groups": groups}
