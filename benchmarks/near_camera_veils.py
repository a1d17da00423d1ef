"""Where a run's test views lose: veils of primitives just in front of the camera, and for the
learned kernel, primitives whose profile the networks switch on in some train views and off in
others.

    python benchmarks/near_camera_veils.py RUN [RUN ...] [--scene PATH] [--close-supports 3] [--json OUT.json]

For each run (a `splatk fit` folder with its model.pt), with the scene loaded as the run loaded it:

* **switched**: the share of primitives whose profile centre d(0) is below 0.1 in some train view
  and above 0.9 in another, and the mean spread (max - min) of d(0) over the train views that
  see a primitive. Analytic kernels have d(0) = 1 in every view, so they switch nothing.
* **per test view**: the alpha that the primitives nearer than a quarter of the visible
  primitives' median depth composite over the image on their own, as a mean over pixels (a veil:
  far background primitives cover whole views by design, near ones should not), and the part of
  it drawn by switched primitives alone; beside it the view's test PSNR from the run's eval.json
  where there is one, the PSNR of the render with the switched primitives left out (black
  background, so it can differ from eval's figure), and the number of primitives whose d(0) in
  the test view is above their highest in any train view by more than 0.2 (Phi_proj
  extrapolating to the new view).
* **close**: the primitives whose centre is nearer the camera than 3x (``--close-supports``) their
  support radius (the kernel's support in sigmas times the largest scale: there EWA splatting's
  first-order projection spreads a primitive far beyond its true footprint), how many there are in
  the test view and in the median train view, and the PSNR of each view on the scene's background
  with them left out, beside the same render with them in.
* **close to a train camera**: of a test view's close primitives, how many are close to a train
  camera too and hold none (no train camera inside their support ellipsoid: the set decision 0118
  relocated in training, all a rule acting in training can see), and the test view's PSNR on the
  background with every primitive of that kind left out.

Prints a table per run and, with ``--json``, writes every figure.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from splatk import backends
from splatk.data import load_scene
from splatk.functional.projection import quats_to_rotmats
from splatk.kernels.base import ViewContext
from splatk.metrics import psnr
from splatk.models.io import load_model

#: "near": nearer than this fraction of the visible primitives' median depth
NEAR_FRACTION = 0.25
#: d(0) below OFF in one train view and above ON in another: switched by the view
OFF, ON = 0.1, 0.9
#: d(0) in a test view this far above its highest in the train views: a new brightness
BRIGHTER = 0.2
#: "close": centre depth below this many times the primitive's support radius
CLOSE_SUPPORTS = 3.0


def centres(model, backend, cam) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(visible, d(0), depth) of every primitive in one view."""
    prims, scales = model.prims, model.scales
    proj = backend.project(prims["means"], prims["quats"], scales, cam.world_to_cam, cam.K, cam.width, cam.height,
                           support_sigmas=model.kernel.support_sigmas, want_view=model.kernel.needs_view)
    if model.kernel.needs_view:
        view = ViewContext(proj.means_cam, scales, proj.rotmats_cam, None)
        centre = model.kernel.samples(model.kernel.project(prims["z3d"], view))[:, 0]
    else:
        centre = torch.ones(len(scales))
    return proj.visible, centre, proj.depths


def render_without(model, backend, cam, drop: torch.Tensor, background: torch.Tensor | None = None):
    """The view rendered on ``background`` (default black) with the primitives in ``drop`` left out."""
    logits = model.prims["opacity_logits"]
    saved = logits.data.clone()
    logits.data[drop] = -30.0
    try:
        return model.render(cam, torch.zeros(3) if background is None else background, backend=backend)
    finally:
        logits.data.copy_(saved)


def alpha_of(model, backend, cam, keep: torch.Tensor) -> float:
    """Mean alpha over the image of the primitives in ``keep`` rendered on their own."""
    return float(render_without(model, backend, cam, ~keep).alpha.mean())


def psnr_without(model, backend, cam, drop: torch.Tensor, background: torch.Tensor | None = None) -> float:
    """PSNR of the view rendered on ``background`` (default black) with the primitives in ``drop``
    left out."""
    image = render_without(model, backend, cam, drop, background).image.clamp(0, 1)
    return float(psnr(image, cam.image_float()))


def close(model, cam, supports: float = CLOSE_SUPPORTS) -> torch.Tensor:
    """The primitives whose centre is in front of the camera and nearer than ``supports`` x their
    support radius. The radius, not the scale, so that kernels of different support (the
    Gaussian's 3 sigma, the learned kernel's 1) compare at the same footprint."""
    depth = (model.prims["means"] @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3])[:, 2]
    radius = model.kernel.support_sigmas * model.scales.max(dim=1).values
    return (depth > 0) & (depth < supports * radius)


def close_to_train_cameras(model, cameras, supports: float = CLOSE_SUPPORTS) -> torch.Tensor:
    """The primitives close to one of ``cameras`` or more (:func:`close`) that hold none of them: no
    camera inside the support ellipsoid (decision 0112's test; cup's backdrop holds its cameras)."""
    means, scales, support = model.prims["means"], model.scales, model.kernel.support_sigmas
    rotations = quats_to_rotmats(model.prims["quats"])
    near = torch.zeros(len(means), dtype=torch.bool)
    holds = torch.zeros_like(near)
    for cam in cameras:
        near |= close(model, cam, supports)
        # the camera centre in each primitive's frame, in its sigmas along the three axes
        local = torch.einsum("nji,nj->ni", rotations, cam.center - means) / scales
        holds |= (local * local).sum(dim=1) <= support * support
    return near & ~holds


@torch.no_grad()
def analyse(run: Path, scene_path: Path | None, supports: float = CLOSE_SUPPORTS) -> dict:
    model, meta = load_model(run / "model.pt")
    scene = load_scene(scene_path or meta["scene"], downscale=meta.get("downscale", 1.0),
                       test_every=meta.get("test_every", 8), eval_split=meta.get("eval_split", "held-out"))
    backend = backends.get("torch", torch.device("cpu"))
    n = model.num_primitives
    lowest, highest = torch.full((n,), 2.0), torch.full((n,), -1.0)
    for cam in scene.train:
        visible, centre, _ = centres(model, backend, cam)
        lowest = torch.where(visible, torch.minimum(lowest, centre), lowest)
        highest = torch.where(visible, torch.maximum(highest, centre), highest)
    seen = highest >= 0
    switched = (lowest < OFF) & (highest > ON)
    evaluated = run / "eval.json"
    eval_psnr = {}
    if evaluated.exists():
        eval_psnr = {v["view"]: v.get("psnr") for v in json.loads(evaluated.read_text())["per_view"]}
    background = torch.tensor(scene.background, dtype=torch.float32)
    close_in_train = sorted(int(close(model, cam, supports).sum()) for cam in scene.train)
    close_to_a_train_camera = close_to_train_cameras(model, scene.train, supports)
    views = []
    for cam in scene.test:
        visible, centre, depth = centres(model, backend, cam)
        near = visible & (depth < NEAR_FRACTION * depth[visible].median())
        close_here = close(model, cam, supports)
        views.append({"view": cam.name, "psnr": eval_psnr.get(cam.name), "near_primitives": int(near.sum()),
                      "near_alpha": alpha_of(model, backend, cam, near),
                      "near_switched_alpha": alpha_of(model, backend, cam, near & switched),
                      "psnr_on_black": psnr_without(model, backend, cam, torch.zeros_like(switched)),
                      "psnr_on_black_without_switched": psnr_without(model, backend, cam, switched),
                      "brighter_than_in_train": int((visible & (centre > highest + BRIGHTER)).sum()),
                      "close_primitives": int(close_here.sum()),
                      "psnr_on_background": psnr_without(model, backend, cam, torch.zeros_like(switched), background),
                      "psnr_on_background_without_close": psnr_without(model, backend, cam, close_here, background),
                      "close_to_a_train_camera": int((close_here & close_to_a_train_camera).sum()),
                      "psnr_on_background_without_train_close": psnr_without(model, backend, cam,
                                                                             close_to_a_train_camera, background)})
    return {"run": str(run), "kernel": meta["spec"]["kernel"], "primitives": n, "close_supports": supports,
            "switched_share": float(switched.sum()) / n,
            "mean_centre_spread": float((highest - lowest)[seen].mean()) if seen.any() else 0.0,
            "close_primitives_median_train_view": close_in_train[len(close_in_train) // 2],
            "close_to_a_train_camera": int(close_to_a_train_camera.sum()),
            "test_views": views}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--scene", type=Path, help="the scene folder, if it moved since the fit")
    ap.add_argument("--close-supports", type=float, default=CLOSE_SUPPORTS,
                    help="the close mark, in support radii (default %(default)s)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [analyse(run, args.scene, args.close_supports) for run in args.runs]
    for r in rows:
        print(f"{r['run']}: {r['kernel']}, {r['primitives']} primitives, switched by view "
              f"{100 * r['switched_share']:.1f} %, mean d(0) spread {r['mean_centre_spread']:.3f}, "
              f"close primitives in the median train view {r['close_primitives_median_train_view']}, "
              f"close to a train camera and holding none {r['close_to_a_train_camera']}")
        print(f"  {'test view':<32} {'PSNR':>6} {'near':>6} {'near alpha':>11} {'of it switched':>15} "
              f"{'on black':>9} {'w/o switched':>13} {'brighter':>9} {'close':>6} {'on bg':>6} {'w/o close':>10} "
              f"{'of close, train-close':>22} {'w/o train-close':>16}")
        for v in r["test_views"]:
            shown = "" if v["psnr"] is None else f"{v['psnr']:.2f}"
            print(f"  {v['view'][-32:]:<32} {shown:>6} {v['near_primitives']:>6} {v['near_alpha']:>11.3f} "
                  f"{v['near_switched_alpha']:>15.3f} {v['psnr_on_black']:>9.2f} "
                  f"{v['psnr_on_black_without_switched']:>13.2f} {v['brighter_than_in_train']:>9} "
                  f"{v['close_primitives']:>6} {v['psnr_on_background']:>6.2f} "
                  f"{v['psnr_on_background_without_close']:>10.2f} {v['close_to_a_train_camera']:>22} "
                  f"{v['psnr_on_background_without_train_close']:>16.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
