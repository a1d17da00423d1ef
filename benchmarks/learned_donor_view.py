"""Does a learned run lose its far test views to Phi_proj's view dependence, or to its geometry?

    python benchmarks/learned_donor_view.py RUN [RUN ...] [--json OUT.json]

For each run of the learned kernel (a `splatk fit` folder with its model.pt), with the scene loaded
as the run loaded it, every test view is rendered twice, on the scene's background:

* **as fitted**: what `splatk eval` measures;
* **train profiles**: the same geometry, opacities and colours, but each primitive draws the
  profile it drew in a train view: the one, among the train views that see it, whose direction to
  the primitive's centre is nearest the test camera's. Phi_proj is then never asked about a view
  it did not train on.

If the second render scores higher, the view dependence the networks extrapolate to the new view
costs that much; if it scores the same, the loss is in what the run put where (geometry,
opacity), which every kernel shares. Also printed: the view's angle to its nearest train camera
(as `gap_by_view_distance.py` measures it) and the mean angle between the test and the donor
directions of the visible primitives, and at the end the median change over the views whose
donors are at least ``FAR_DEG`` away and over the others. ``--json`` writes every figure.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from splatk import backends
from splatk.data import load_scene
from splatk.functional.projection import quats_to_rotmats
from splatk.kernels.base import ViewContext
from splatk.metrics import psnr
from splatk.models.io import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gap_by_view_distance import camera_pose, view_angles


def visible_in(model, backend, cam) -> torch.Tensor:
    prims = model.prims
    return backend.project(prims["means"], prims["quats"], model.scales, cam.world_to_cam, cam.K, cam.width,
                           cam.height, support_sigmas=model.kernel.support_sigmas).visible


#: the summary splits test views at this mean angle between their and their donors' directions
FAR_DEG = 10.0


@torch.no_grad()
def donors(model, backend, train, test_cam) -> tuple[torch.Tensor, torch.Tensor]:
    """([N] index into ``train`` of each primitive's donor view, -1 where no train view sees it;
    [N] the angle in degrees between the test and the donor direction)."""
    means = model.prims["means"]
    to_test = F.normalize(means - camera_pose(test_cam)[0], dim=1)
    best = torch.full((len(means),), -2.0)
    donor = torch.full((len(means),), -1, dtype=torch.long)
    for t, cam in enumerate(train):
        cosine = (F.normalize(means - camera_pose(cam)[0], dim=1) * to_test).sum(1)
        better = visible_in(model, backend, cam) & (cosine > best)
        best = torch.where(better, cosine, best)
        donor = torch.where(better, torch.full_like(donor, t), donor)
    return donor, torch.rad2deg(torch.acos(best.clamp(-1, 1)))


@torch.no_grad()
def render_with_train_profiles(model, backend, train, test_cam, background) -> tuple[torch.Tensor, float]:
    """The test view drawn with each primitive's profile as its donor train view computes it."""
    donor, angle = donors(model, backend, train, test_cam)
    prims = model.prims
    means, rot = prims["means"], quats_to_rotmats(prims["quats"])
    # each primitive in its donor camera's frame (itself in the test camera's where none sees it)
    viewmats = torch.stack([test_cam.world_to_cam] + [cam.world_to_cam for cam in train])[donor + 1]
    means_cam = (viewmats[:, :3, :3] @ means[:, :, None])[:, :, 0] + viewmats[:, :3, 3]
    rot_cam = viewmats[:, :3, :3] @ rot
    idx = torch.nonzero(visible_in(model, backend, test_cam)).flatten()  # the rows render() keeps
    kernel = model.kernel
    fitted_profile = kernel.profile

    def donor_profile(vis, view):
        return fitted_profile(vis, ViewContext(means_cam.index_select(0, idx), view.scales,
                                               rot_cam.index_select(0, idx), view.backend))

    kernel.profile = donor_profile
    try:
        image = model.render(test_cam, background, backend=backend).image.clamp(0, 1)
    finally:
        del kernel.profile
    seen = donor[idx] >= 0
    return image, float(angle[idx][seen].mean()) if seen.any() else math.nan


def load_learned_run(run: Path):
    """(model, meta, scene, background) of a learned run, the scene loaded as the run loaded it and
    its train views the ones the run trained on."""
    model, meta = load_model(run / "model.pt")
    if not model.kernel.needs_view:
        raise SystemExit(f"{run}: kernel {meta['spec']['kernel']} has no view dependence")
    scene = load_scene(meta["scene"], downscale=meta.get("downscale", 1.0), test_every=meta.get("test_every", 8),
                       background=tuple(meta["background"]) if meta.get("background") else None,
                       eval_split=meta.get("eval_split", "held-out"))
    fitted_summary = run / "fit.json"
    stride = json.loads(fitted_summary.read_text()).get("view_stride", 1) if fitted_summary.is_file() else 1
    scene.train = scene.train[::stride]
    return model, meta, scene, torch.tensor(scene.background, dtype=torch.float32)


@torch.no_grad()
def analyse(run: Path) -> dict:
    model, meta, scene, background = load_learned_run(run)
    backend = backends.get("auto", torch.device("cpu"))
    angles = view_angles(scene)
    views = []
    for cam in scene.test:
        target = cam.image_float()
        fitted = model.render(cam, background, backend=backend).image.clamp(0, 1)
        swapped, donor_angle = render_with_train_profiles(model, backend, scene.train, cam, background)
        views.append({"view": cam.name, "angle_to_train_deg": angles.get(cam.name),
                      "psnr_as_fitted": float(psnr(fitted, target)),
                      "psnr_train_profiles": float(psnr(swapped, target)),
                      "mean_donor_angle_deg": donor_angle})
    return {"run": str(run), "scene": str(meta["scene"]),
            "k": model.kernel.k, "test_views": views}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [analyse(run) for run in args.runs]
    for r in rows:
        print(f"{r['run']} (k = {r['k']})")
        print(f"  {'test view':<28} {'to train':>9} {'as fitted':>10} {'train profiles':>15} {'change':>7} "
              f"{'donor angle':>12}")
        for v in r["test_views"]:
            print(f"  {v['view'][-28:]:<28} {v['angle_to_train_deg']:>8.1f}° {v['psnr_as_fitted']:>10.2f} "
                  f"{v['psnr_train_profiles']:>15.2f} {v['psnr_train_profiles'] - v['psnr_as_fitted']:>+7.2f} "
                  f"{v['mean_donor_angle_deg']:>11.1f}°")
    views = [v for r in rows for v in r["test_views"]]
    for far, label in ((True, f"at least {FAR_DEG:g}°"), (False, f"under {FAR_DEG:g}°")):
        changes = [v["psnr_train_profiles"] - v["psnr_as_fitted"] for v in views
                   if (v["mean_donor_angle_deg"] >= FAR_DEG) == far]
        if changes:
            print(f"test views whose donors are {label} away: {len(changes)}, change median "
                  f"{statistics.median(changes):+.2f} dB, raised in {sum(c > 0 for c in changes)}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
