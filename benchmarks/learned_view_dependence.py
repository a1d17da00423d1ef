"""How much of a learned-kernel run's test PSNR its view dependence carries, and whether its losses
come from Phi_proj extrapolating past the train views.

    python benchmarks/learned_view_dependence.py RUN [RUN ...] [--json OUT.json]

Each run (a `splatk fit` folder of the learned kernel, with its model.pt) is first rendered in every
train view, recording each primitive's profile table there. Its test views are then rendered, with
the scene's background and the fastest backend as `splatk eval` renders them, three ways:

* **as fitted**: the profile Phi_proj and Phi_dec give for the test view (`splatk eval`'s figure);
* **capped**: each primitive's profile scaled so its centre d(0) is at most the highest d(0) it had
  in any train view that saw it. A primitive drawn brighter in a test view than in every train view
  is Phi_proj extrapolating; the cap removes exactly that and leaves the rest as fitted;
* **view-averaged**: each primitive's profile replaced by its mean table over the train views that
  saw it (primitives no train view saw keep theirs): the same primitives with the view dependence
  taken out after the fit.

Beside them, **turn change**: the mean squared change of the visible primitives' profile tables
when each primitive is turned by 10 degrees about a random axis (its camera-space rotation turned,
its centre kept: the camera orbiting it), over the train views. It measures how steeply the fitted
profiles change with the view.

Prints each way's mean test PSNR and the turn change per run; ``--json`` writes them and every
view's figures.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
from pathlib import Path

import torch
from torch import nn

from splatk import backends
from splatk.backends import Profile
from splatk.data import load_scene
from splatk.functional.projection import quats_to_rotmats
from splatk.kernels import ViewContext
from splatk.metrics import psnr
from splatk.models.io import load_model

#: a temporary per-primitive entry that tells the profile hook which primitives it was handed
INDEX_KEY = "_primitive_index"
#: the turn of the turn change, in degrees
TURN_DEG = 10.0


def random_rotations(n: int, degrees: float, generator: torch.Generator) -> torch.Tensor:
    """``n`` rotations [n, 3, 3] by ``degrees`` about uniformly random axes."""
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=1)
    half = math.radians(degrees) / 2
    return quats_to_rotmats(torch.cat([torch.full((n, 1), math.cos(half)), math.sin(half) * axis], 1))


@torch.no_grad()
def turn_change(model, backend, cams, degrees: float = TURN_DEG, seed: int = 0) -> float:
    """Mean over ``cams`` of the visible primitives' mean squared profile change under a turn."""
    kernel, prims, scales = model.kernel, model.prims, model.scales
    generator = torch.Generator().manual_seed(seed)
    changes = []
    for cam in cams:
        proj = backend.project(prims["means"], prims["quats"], scales, cam.world_to_cam, cam.K, cam.width,
                               cam.height, support_sigmas=kernel.support_sigmas, want_view=True)
        idx = torch.nonzero(proj.visible).flatten()
        if len(idx) == 0:
            continue
        z3d = prims["z3d"].index_select(0, idx) if "z3d" in prims else None
        view = ViewContext(proj.means_cam[idx], scales[idx], proj.rotmats_cam[idx], None)
        turned = ViewContext(view.means_cam, view.scales,
                             random_rotations(len(idx), degrees, generator) @ view.rotmats_cam, None)
        table = kernel.samples(kernel.project(z3d, view))
        changes.append(float((table - kernel.samples(kernel.project(z3d, turned))).square().mean()))
    return sum(changes) / max(len(changes), 1)


@contextlib.contextmanager
def profile_hook(model, hook):
    """Within the block, every render passes the kernel's profile table [M, k] of the visible
    primitives through ``hook(indices [M], table) -> table``."""
    kernel = model.kernel
    fitted = kernel.profile
    n = model.num_primitives
    model.prims[INDEX_KEY] = nn.Parameter(torch.arange(n, dtype=torch.float32), requires_grad=False)

    def profile(prims, view):
        table = fitted(prims, view).params
        return Profile("table", hook(prims[INDEX_KEY].long(), table))

    kernel.profile = profile
    try:
        yield
    finally:
        del kernel.profile  # the class's method again
        del model.prims[INDEX_KEY]


class TrainViewProfiles:
    """Each primitive's profile tables over the train views: :meth:`record` is the hook to render
    them with; :meth:`capped` and :meth:`view_averaged` are the hooks for the test views."""

    def __init__(self, num_primitives: int, k: int):
        self.highest_centre = torch.zeros(num_primitives)
        self.table_sum = torch.zeros(num_primitives, k)
        self.seen_in = torch.zeros(num_primitives)

    def record(self, index: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        self.highest_centre.scatter_reduce_(0, index, table[:, 0].float(), "amax")
        self.table_sum.index_add_(0, index, table.float())
        self.seen_in.index_add_(0, index, torch.ones(len(index)))
        return table

    def capped(self, index: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        ceiling = self.highest_centre.index_select(0, index)
        factor = (ceiling / table[:, 0].float().clamp_min(1e-12)).clamp(max=1.0)
        return table * factor[:, None].to(table.dtype)

    def view_averaged(self, index: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        count = self.seen_in.index_select(0, index)
        mean = self.table_sum.index_select(0, index) / count.clamp_min(1.0)[:, None]
        return torch.where(count[:, None] > 0, mean.to(table.dtype), table)


@torch.no_grad()
def analyse(run: Path) -> dict:
    model, meta = load_model(run / "model.pt")
    if meta["spec"]["kernel"] != "learned":
        raise SystemExit(f"{run}: a {meta['spec']['kernel']} run; this compares the learned kernel's views")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
    backend = backends.get("auto", "cpu")
    background = torch.tensor(scene.background, dtype=torch.float32)
    n, k = model.num_primitives, model.kernel.k
    train = TrainViewProfiles(n, k)

    with profile_hook(model, train.record):
        for cam in scene.train:
            model.render(cam, background, backend=backend)

    def test_psnr(cam) -> float:
        image = model.render(cam, background, backend=backend).image.clamp(0, 1)
        return float(psnr(image, cam.image_float()))

    views = []
    for cam in scene.test:
        row = {"view": cam.name, "as_fitted": test_psnr(cam)}
        with profile_hook(model, train.capped):
            row["capped"] = test_psnr(cam)
        with profile_hook(model, train.view_averaged):
            row["view_averaged"] = test_psnr(cam)
        views.append(row)
    mean = {way: sum(v[way] for v in views) / len(views) for way in ("as_fitted", "capped", "view_averaged")}
    return {"run": str(run), "scene": meta["scene"], "primitives": n, "k": k, "backend": backend.name,
            "mean": mean, "turn_change": turn_change(model, backends.get("torch", "cpu"), scene.train),
            "turn_deg": TURN_DEG, "test_views": views}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    print(f"{'run':<56} {'as fitted':>9} {'capped':>8} {'diff':>7} {'view-avg':>9} {'diff':>7} {'turn change':>12}")
    for run in args.runs:
        r = analyse(run)
        rows.append(r)
        m = r["mean"]
        print(f"{str(run)[-56:]:<56} {m['as_fitted']:>9.2f} {m['capped']:>8.2f} "
              f"{m['capped'] - m['as_fitted']:>+7.3f} {m['view_averaged']:>9.2f} "
              f"{m['view_averaged'] - m['as_fitted']:>+7.2f} {r['turn_change']:>12.4f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
