"""Density-control strategies, registered by name: ``mcmc`` (DBS / 3DGS-MCMC relocation and
growth to a budget, :mod:`splatk.train.mcmc`) and ``adc`` (3DGS's clone, split, prune and
opacity reset, :mod:`splatk.train.adc`). ``TrainConfig.strategy`` picks one; a new strategy is
one module with a registered :class:`Strategy` subclass, imported by :mod:`splatk.train.trainer`
(which imports each strategy's settings class from its module).
"""
from __future__ import annotations

import torch


class Strategy:
    """What the trainer asks of a density-control strategy each iteration."""

    name = "base"
    #: per-primitive statistics that :meth:`observe` accumulates ([N] tensor attributes, None
    #: until the first), by name, and how the ranks of a data-parallel run combine what each
    #: observed of its own views: "sum" or "max" (splatk.train.distributed)
    statistics: dict[str, str] = {}

    @classmethod
    def from_train_config(cls, config, scene, backend) -> "Strategy":
        """The strategy ``config`` (a TrainConfig) asks for, for ``scene`` (its extent, background
        and train views), drawing with the run's ``backend`` where it renders."""
        raise NotImplementedError

    def observe(self, it: int, model, render, camera) -> None:
        """After the loss's backward pass: statistics of the view just rendered (``render``: the
        model's RenderResult, gradients filled in). Default: none kept."""

    def step(self, it: int, progress: float, model, opt, means_lr: float,
             generator: torch.Generator | None = None) -> None:
        """Edit the model's primitives (through ``opt``, which keeps Adam's moments in step)."""
        raise NotImplementedError

    def raised_loss(self) -> bool:
        """True when the last :meth:`step` raised the loss on purpose (3DGS's opacity reset):
        the trainer's guard then judges the loss afresh instead of rolling the step back."""
        return False

    def state_dict(self) -> dict:
        """Statistics a checkpoint must keep for a resume to continue exactly."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


STRATEGIES: dict[str, type[Strategy]] = {}


def register_strategy(cls: type[Strategy]) -> type[Strategy]:
    STRATEGIES[cls.name] = cls
    return cls


def make_strategy(config, scene, backend) -> Strategy:
    if config.strategy not in STRATEGIES:
        raise ValueError(f"unknown density control {config.strategy!r}; choose from {', '.join(sorted(STRATEGIES))}")
    return STRATEGIES[config.strategy].from_train_config(config, scene, backend)

