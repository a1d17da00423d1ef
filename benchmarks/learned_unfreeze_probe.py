"""What the learned kernel's training does at and after its networks unfreeze.

    python benchmarks/learned_unfreeze_probe.py SCENE OUT.json [--iters 7000] [--stop 3000]
        [--downscale 2] [--budget 20000] [--k 2] [--sh-degree 3] [--every 100] [--threads 1]
        [--kernel-option name=value ...] [--train-option name=value ...] [--keep-net proj|dec]

Builds the trainer as ``splatk fit SCENE --kernel learned`` does (short-run schedules and learning
rates included; ``--no-short-run-lrs`` keeps the 30k ones) and, every ``--every`` iterations, writes
to OUT.json:

* the loss (mean over the interval), the train PSNR, the step sizes in force;
* per parameter group, the RMS of one Adam update (per-primitive tensors) and, for the two
  networks, the gradient norm, the update norm and the drift from the pretrained weights;
* the latents z3d (RMS, 99th percentile of the norm) and the 2D latents z2d (RMS);
* the profile each primitive ends with on ``--views`` train views: mean d(0) and d(r=1), the mean
  profile over d(0) at the k radii, the share that rises anywhere inside the support, the share
  whose profile rises outwards (d(1) > d(0)), the share that fills its support to the edge
  (d(1) > 0.5), and the view-dependence (per primitive std of d(0), d(1) over those views);
* scales (median log scale relative to the extent), opacities (mean, share dead), and MCMC's
  relocation counts and the trainer's events.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import torch

from splatk.data import load_scene
from splatk.functional.projection import project_ellipsoids
from splatk.kernels.base import ViewContext
from splatk.stages.autobudget import render_psnr
from splatk.stages.fit import FitConfig, build_model
from splatk.stages.run_length import boost_short_run_lrs, scale_schedules_to_run
from splatk.train.trainer import Trainer


def _parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(text.lower(), text)


def _options(pairs: list[str]) -> dict:
    out = {}
    for pair in pairs:
        name, _, value = pair.partition("=")
        out[name] = _parse_value(value)
    return out


@torch.no_grad()
def profile_stats(model, cameras) -> dict:
    """Profiles of every primitive on ``cameras`` (fp32 torch path) and their spread over views."""
    kernel = model.kernel
    n = model.num_primitives
    d0 = torch.full((len(cameras), n), float("nan"))
    d1 = torch.full((len(cameras), n), float("nan"))
    z2d_sq, shapes, rising_inside = [], [], []
    for i, cam in enumerate(cameras):
        proj = project_ellipsoids(model.prims["means"], model.prims["quats"], model.scales,
                                  cam.world_to_cam, cam.K, cam.width, cam.height,
                                  support_sigmas=kernel.support_sigmas)
        idx = torch.nonzero(proj.visible).flatten()
        view = ViewContext(proj.means_cam[idx], model.scales[idx], proj.rotmats_cam[idx])
        z3d = model.prims["z3d"][idx] if "z3d" in model.prims else None
        z2d = kernel.proj(kernel.encode(z3d, view))
        table = kernel.samples(z2d)  # the table the rasteriser draws
        d0[i, idx], d1[i, idx] = table[:, 0], table[:, -1]
        shapes.append(table / table[:, :1].clamp_min(1e-6))
        rising_inside.append((table[:, 1:] > table[:, :-1] + 1e-3).any(1).float())
        z2d_sq.append((z2d ** 2).mean())
    seen = ~torch.isnan(d0)
    v0, v1 = d0[seen], d1[seen]
    multi = seen.sum(0) >= 2

    def view_std(d):
        mean = torch.nanmean(d, 0, keepdim=True)
        var = torch.nansum((d - mean) ** 2, 0) / (seen.sum(0) - 1).clamp_min(1)
        return float(var[multi].sqrt().mean()) if multi.any() else 0.0

    return {"d0_mean": float(v0.mean()), "d1_mean": float(v1.mean()),
            "rising_share": float((v1 > v0).float().mean()), "filled_share": float((v1 > 0.5).float().mean()),
            "d0_view_std": view_std(d0), "d1_view_std": view_std(d1),
            "z2d_rms": float(torch.stack(z2d_sq).mean().sqrt()),
            # the mean profile, each sample over the primitive's d(0), and the share of profiles
            # that rise somewhere inside the support (k > 2 only)
            "shape_mean": [round(float(v), 4) for v in torch.cat(shapes).mean(0)],
            "rising_inside_share": float(torch.cat(rising_inside).mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("out", type=Path)
    ap.add_argument("--iters", type=int, default=7000)
    ap.add_argument("--stop", type=int, default=None, help="stop after this many iterations")
    ap.add_argument("--downscale", type=float, default=2.0)
    ap.add_argument("--budget", type=int, default=20000)
    ap.add_argument("--k", type=int, default=2)
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--views", type=int, default=4, help="train views the profiles are probed on")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-short-run-lrs", action="store_true")
    ap.add_argument("--keep-net", choices=("proj", "dec"), default=None,
                    help="keep this network at its pretrained weights (the other trains)")
    ap.add_argument("--save-at", default="", help="comma-separated iterations at which to save the "
                    "trainer's state next to OUT (OUT.itN.pt)")
    ap.add_argument("--detach-geometry", action="store_true",
                    help="no gradient from Phi_proj's inputs into the means, scales and rotations")
    ap.add_argument("--kernel-option", action="append", default=[])
    ap.add_argument("--train-option", action="append", default=[])
    a = ap.parse_args()

    torch.set_num_threads(a.threads)
    cfg = FitConfig(kernel="learned", downscale=a.downscale, threads=a.threads, sh_degree=a.sh_degree)
    cfg.kernel_options = {"k": a.k, **_options(a.kernel_option)}
    cfg.train.iters, cfg.train.budget = a.iters, a.budget
    for name, value in _options(a.train_option).items():
        setattr(cfg.train, name, value)
    changed = scale_schedules_to_run(cfg)
    if not a.no_short_run_lrs:
        changed.update(boost_short_run_lrs(cfg))
    scene = load_scene(a.scene, downscale=cfg.downscale, test_every=cfg.test_every)
    torch.manual_seed(cfg.train.seed)
    model = build_model(scene, cfg)
    trainer = Trainer(scene, model, cfg.train)
    kernel = trainer.model.kernel
    if a.keep_net:  # Adam skips parameters that get no gradient
        for p in getattr(kernel, a.keep_net).parameters():
            p.requires_grad_(False)
    if a.detach_geometry:
        encode = kernel.encode

        def detached_encode(z3d, view):
            return encode(z3d, dataclasses.replace(view, means_cam=view.means_cam.detach(),
                                                   scales=view.scales.detach(), rotmats_cam=view.rotmats_cam.detach()))
        kernel.encode = detached_encode
    probe_cams = scene.train[:: max(1, len(scene.train) // a.views)][: a.views]
    nets = {"proj": list(kernel.proj.parameters()), "dec": list(kernel.dec.parameters())}
    start = {k: [p.detach().clone() for p in ps] for k, ps in nets.items()}

    def flat_norm(tensors) -> float:
        return math.sqrt(sum(float((t ** 2).sum()) for t in tensors))

    # one Adam update's size per group, measured at the probe's iterations
    measure = {"on": False, "prim": {}, "net": {}}
    prim_step, net_step = trainer.opt.step, trainer.net_opt.step

    def timed_prim_step():
        if not measure["on"]:
            return prim_step()
        before = {k: v.detach().clone() for k, v in trainer.model.prims.items()}
        prim_step()
        measure["prim"] = {k: float((trainer.model.prims[k].detach() - before[k]).pow(2).mean().sqrt())
                           for k in before}

    def timed_net_step():
        if not measure["on"]:
            return net_step()
        measure["net"] = {k: {"grad_norm": flat_norm([p.grad for p in ps if p.grad is not None])}
                          for k, ps in nets.items()}
        before = {k: [p.detach().clone() for p in ps] for k, ps in nets.items()}
        net_step()
        for k, ps in nets.items():
            measure["net"][k]["update_norm"] = flat_norm([p.detach() - b for p, b in zip(ps, before[k])])

    def rebind():  # a rollback rebuilds the optimisers
        nonlocal prim_step, net_step
        if trainer.opt.step is not timed_prim_step:
            prim_step, net_step = trainer.opt.step, trainer.net_opt.step
            trainer.opt.step, trainer.net_opt.step = timed_prim_step, timed_net_step

    rebind()

    def write(test_psnr):
        a.out.write_text(json.dumps({"args": vars(a) | {"out": str(a.out)}, "schedules": changed,
                                     "kernel_options": kernel.options, "events": trainer.events,
                                     "seconds": time.time() - t0, "test_psnr": test_psnr,
                                     "records": records}, indent=1))

    records, losses, psnrs, relocations = [], [], [], []
    stop = a.stop or a.iters
    t0 = time.time()
    while not trainer.done() and trainer.it < stop:
        measure["on"] = (trainer.it + 1) % a.every == 0
        measure["net"] = {}
        info = trainer.train_step()
        rebind()
        if str(info.it) in a.save_at.split(","):
            torch.save(trainer.state_dict(), a.out.with_suffix(f".it{info.it}.pt"))
        losses.append(info.loss)
        psnrs.append(info.psnr)
        stats = trainer.strategy.last_stats
        if trainer.strategy.is_refine_step(info.it, info.progress) and stats:
            relocations.append(stats["relocated"])
        if info.it % a.every and not info.event:
            continue
        prims = trainer.model.prims
        z = prims["z3d"].detach()
        op = torch.sigmoid(prims["opacity_logits"].detach())
        rec = {
            "it": info.it, "loss": sum(losses) / max(1, len(losses)), "train_psnr": sum(psnrs) / max(1, len(psnrs)),
            "num": info.num_primitives, "event": info.event, "lr_scale": trainer.lr_scale,
            "net_lr": trainer.net_opt.param_groups[0]["lr"],
            "z3d_lr": next(g["lr"] for g in trainer.opt.opt.param_groups if g["name"] == "z3d"),
            "update_rms": dict(measure["prim"]), "nets": dict(measure["net"]),
            "net_drift": {k: flat_norm([p.detach() - s for p, s in zip(ps, start[k])]) / flat_norm(start[k])
                          for k, ps in nets.items()},
            "z3d_rms": float(z.pow(2).mean().sqrt()),
            "z3d_norm_p99": float(torch.quantile(z.norm(dim=1), 0.99)),
            "log_scale_rel_median": float((prims["log_scales"].detach().max(1).values
                                           - math.log(trainer.extent)).median()),
            "opacity_mean": float(op.mean()), "dead_share": float((op <= 0.005).float().mean()),
            "relocated": sum(relocations),
            **profile_stats(trainer.model, probe_cams),
        }
        records.append(rec)
        losses, psnrs, relocations = [], [], []
        print(json.dumps({k: rec[k] for k in ("it", "loss", "train_psnr", "net_lr", "d0_mean", "d1_mean",
                                               "rising_share", "z3d_rms", "event")}), flush=True)
        write(None)

    write(render_psnr(trainer.model, scene.test, scene.background, trainer.backend))


if __name__ == "__main__":
    main()
