"""Adam over per-primitive tensors that can be relocated, grown and reset row by row."""
from __future__ import annotations

import torch
from torch import nn


def _adam(groups) -> torch.optim.Adam:
    """Adam with eps 1e-15; the fused implementation (one kernel for all moments, 4x faster on
    the CPU at 50k primitives) where this torch has it, the default one elsewhere."""
    try:
        return torch.optim.Adam(groups, eps=1e-15, fused=True)
    except (RuntimeError, TypeError, ValueError):  # older torch, or a device without it
        return torch.optim.Adam(groups, eps=1e-15)


class PrimitiveAdam:
    """One Adam param group per per-primitive tensor (3DGS style), eps 1e-15.

    Density control rewrites rows (relocation) and appends rows (growth); this class keeps the
    Adam moments in step with those edits.
    """

    def __init__(self, prims: nn.ParameterDict, lrs: dict[str, float]):
        self.prims = prims
        groups = [{"params": [prims[name]], "lr": lrs[name], "name": name} for name in prims.keys()]
        self.opt = _adam(groups)
        self.base_lrs = dict(lrs)

    def zero_grad(self) -> None:
        self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.opt.step()

    def set_lr(self, name: str, lr: float) -> None:
        for g in self.opt.param_groups:
            if g["name"] == name:
                g["lr"] = lr

    def _group(self, name):
        for g in self.opt.param_groups:
            if g["name"] == name:
                return g
        raise KeyError(name)

    @torch.no_grad()
    def reset_moments(self, rows: torch.Tensor) -> None:
        """Zero Adam's moments of ``rows`` in every tensor (relocated primitives start fresh)."""
        for g in self.opt.param_groups:
            st = self.opt.state.get(g["params"][0])
            if st:
                st["exp_avg"][rows] = 0
                st["exp_avg_sq"][rows] = 0

    @torch.no_grad()
    def reset_moments_of(self, name: str) -> None:
        """Zero Adam's moments of one tensor (3DGS's opacity reset)."""
        st = self.opt.state.get(self._group(name)["params"][0])
        if st:
            st["exp_avg"].zero_()
            st["exp_avg_sq"].zero_()

    @torch.no_grad()
    def keep_rows(self, keep: torch.Tensor) -> None:
        """Keep only the rows ``keep`` selects ([N] mask or indices) in every per-primitive tensor,
        with their Adam moments (pruning, compaction)."""
        for g in self.opt.param_groups:
            old = g["params"][0]
            new = nn.Parameter(old.data[keep].clone())
            st = self.opt.state.pop(old, None)
            if st:
                for key in ("exp_avg", "exp_avg_sq"):
                    st[key] = st[key][keep].clone()
                self.opt.state[new] = st
            g["params"][0] = new
            self.prims[g["name"]] = new

    @torch.no_grad()
    def append_rows(self, new_rows: dict[str, torch.Tensor]) -> None:
        """Append rows to every per-primitive tensor, with zero Adam moments."""
        for name, rows in new_rows.items():
            g = self._group(name)
            old = g["params"][0]
            new = nn.Parameter(torch.cat([old.data, rows.to(old.dtype)], 0))
            st = self.opt.state.pop(old, None)
            if st:
                for key in ("exp_avg", "exp_avg_sq"):
                    st[key] = torch.cat([st[key], torch.zeros_like(rows, dtype=st[key].dtype)], 0)
                self.opt.state[new] = st
            g["params"][0] = new
            self.prims[name] = new

    def state_dict(self) -> dict:
        return self.opt.state_dict()

    def load_state_dict(self, sd: dict) -> None:
        self.opt.load_state_dict(sd)
