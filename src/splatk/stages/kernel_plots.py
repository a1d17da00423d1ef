"""`splatk export RUN --format kernels --out DIR`: what the kernels of a run look like.

Writes, into DIR:

* ``profiles.png``: 1D profiles d(r) of a few primitives, one curve per view (paper Fig. 3):
  solid = the profile the rasteriser draws (for the learned kernel: the k samples, linearly
  interpolated in r), dashed = Phi_dec(r^2, z2d) itself (learned kernel only).
* ``d1_histograms.png``: per view, the rendered image above a histogram of
  d1 = Phi_dec(0, z2d) over the visible primitives, mean as a red dotted line, horizontal
  axis [0, 1] (paper Figs. 5-6). Fixed kernels are plotted the same way (their d1 is 1).
* ``kernels.json``: the numbers behind both figures.

Views are spread evenly over the run's scene cameras; if the scene folder is gone, over an
orbit around the primitives (``views_source`` in the JSON says which).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from .. import backends
from ..backends.profiles import evaluate_profile
from ..data.types import Camera
from ..functional.projection import project_ellipsoids
from ..kernels import ViewContext
from ..models.io import load_model

#: radii of the plotted / stored curves
CURVE_POINTS = 65
JSON_POINTS = 21
HIST_BINS = 40


def _scene_cameras(meta: dict, scene_path) -> tuple[list[Camera], str, tuple]:
    """The run's cameras (train + test, name order), or an orbit if the scene is gone."""
    from ..data import load_scene

    scene_path = scene_path or meta.get("scene")
    if scene_path and Path(scene_path).exists():
        scene = load_scene(scene_path, downscale=meta.get("downscale", 1.0),
                           test_every=meta.get("test_every", 8),
                           background=tuple(meta["background"]) if meta.get("background") else None,
                           load_images=False)
        cams = sorted(scene.train + scene.test, key=lambda c: c.name)
        return cams, "scene", tuple(scene.background)
    return [], "orbit", tuple(meta.get("background") or (0.0, 0.0, 0.0))


def orbit_cameras(means: torch.Tensor, n: int, size: int = 256, fov_deg: float = 50.0) -> list[Camera]:
    """``n`` cameras on a circle around the primitives (z up), looking at their median."""
    center = means.median(0).values.double()
    spread = (means.double() - center).norm(dim=1).quantile(0.9).clamp_min(1e-6)
    radius = 2.5 * float(spread)
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = center + torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.4 * radius],
                                    dtype=torch.float64)
        fwd = (center - eye) / (center - eye).norm()
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(fwd, right)
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3] = torch.stack([right, down, fwd])
        M[:3, 3] = -M[:3, :3] @ eye
        cams.append(Camera(f"orbit_{i:02d}", size, size, f, f, size / 2, size / 2, M.float()))
    return cams


@torch.no_grad()
def view_profiles(model, cam: Camera):
    """Visible indices [M], the Profile for them, and z2d [M, L] (learned kernel) or None."""
    scales = model.scales
    proj = project_ellipsoids(
        model.prims["means"], model.prims["quats"], scales, cam.world_to_cam, cam.K,
        cam.width, cam.height, support_sigmas=model.kernel.support_sigmas,
    )
    idx = torch.nonzero(proj.visible).flatten()
    vis = {k: v[idx] for k, v in model.prims.items()}
    view = ViewContext(proj.means_cam[idx], scales[idx], proj.rotmats_cam[idx])
    profile = model.kernel.profile(vis, view)
    z2d = model.kernel.project(vis.get("z3d"), view) if hasattr(model.kernel, "project") else None
    return idx, profile, z2d


def _curves(profile, rows: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Profile values [len(rows), len(r)] of the given visible rows, as the rasteriser draws."""
    g = rows.repeat_interleave(len(r))
    r2 = (r * r).repeat(len(rows))
    params = None if profile.params is None else profile.params[g]
    return evaluate_profile(profile.kind, r2, params).view(len(rows), len(r))


#: the marker kind of a kernel-plots folder (``splatk.outputs``)
KERNEL_PLOTS_KIND = "kernel plots"


def export_kernel_plots(
    run: str | Path,
    out: str | Path,
    backend: str = "auto",
    scene_path: str | Path | None = None,
    num_views: int = 6,
    num_primitives: int = 4,
    render: bool = True,
    overwrite: bool = False,
) -> Path:
    """Write the kernel figures and ``kernels.json`` for RUN into folder ``out`` (new, empty, or
    with ``overwrite`` an earlier kernel-plots export); returns it. Arguments as
    :func:`_write_kernel_plots`'s."""
    from ..outputs import OutputDir, check_output_dir

    inputs = [Path(run), scene_path]
    check_output_dir(Path(out), KERNEL_PLOTS_KIND, overwrite, inputs=inputs)
    with OutputDir(Path(out), KERNEL_PLOTS_KIND, overwrite, inputs=inputs):
        return _write_kernel_plots(run, out, backend, scene_path, num_views, num_primitives, render)


def _write_kernel_plots(run: str | Path, out: str | Path, backend: str, scene_path: str | Path | None,
                        num_views: int, num_primitives: int, render: bool) -> Path:
    """Write the kernel figures and ``kernels.json`` for RUN into folder ``out``; returns it.

    Args:
        run: run folder (with model.pt).
        out: output folder (created).
        backend: rasteriser for the view thumbnails.
        scene_path: the scene, if it moved since `splatk fit` (default: the run's).
        num_views: views to show, spread evenly over the cameras.
        num_primitives: primitives in the profile figure (those seen in most chosen views,
            then the most opaque).
        render: draw each view's rendered image above its histogram.
    """
    import matplotlib
    # the Agg canvas directly: no pyplot, so no global backend state is touched
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    run = Path(run)
    out = Path(out)
    model, meta = load_model(run / "model.pt")
    if getattr(model, "primitive", "volumetric") == "planar":
        from ..errors import InputError

        # the figures show radial profiles of volumetric kernels; a surfel kernel is 2D (u, v)
        raise InputError(run / "model.pt", "kernel plots of planar (surfel) models are not supported",
                         "use `splatk export --format renders`")
    model.eval()
    cams, source, background = _scene_cameras(meta, scene_path)
    if not cams:
        cams = orbit_cameras(model.prims["means"].detach(), num_views)
    pick = np.unique(np.linspace(0, len(cams) - 1, min(num_views, len(cams))).round().astype(int))
    cams = [cams[i] for i in pick]
    out.mkdir(parents=True, exist_ok=True)
    kernel = model.kernel
    learned = hasattr(kernel, "decode")
    r = torch.linspace(0.0, 1.0, CURVE_POINTS)
    r_json = torch.linspace(0.0, 1.0, JSON_POINTS)

    per_view = []
    with torch.no_grad():
        for cam in cams:
            idx, profile, z2d = view_profiles(model, cam)
            d1 = _curves(profile, torch.arange(len(idx)), torch.zeros(1))[:, 0] if len(idx) else torch.zeros(0)
            per_view.append({"cam": cam, "idx": idx, "profile": profile, "z2d": z2d, "d1": d1})

    # primitives seen in most views, then the most opaque
    n = model.num_primitives
    seen = torch.zeros(n)
    for v in per_view:
        seen[v["idx"]] += 1
    score = seen * 2.0 + model.opacities.detach()
    chosen = [int(i) for i in torch.argsort(score, descending=True)[:num_primitives] if seen[i] > 0]

    # ---- figure: profiles (paper Fig. 3) ---------------------------------------------
    colors = matplotlib.colormaps["viridis"](np.linspace(0.0, 0.9, len(per_view)))
    ncols = max(1, len(chosen))
    fig = Figure(figsize=(3.2 * ncols, 3.0), layout="constrained")
    FigureCanvasAgg(fig)
    prim_json = []
    for j, g in enumerate(chosen):
        ax = fig.add_subplot(1, ncols, j + 1)
        entry = {"index": g, "opacity": float(model.opacities[g].detach()), "views": {}}
        for v, col in zip(per_view, colors):
            hit = torch.nonzero(v["idx"] == g).flatten()
            if len(hit) == 0:
                continue
            row = hit[:1]
            with torch.no_grad():
                drawn = _curves(v["profile"], row, r)[0]
                ax.plot(r.numpy(), drawn.numpy(), color=col, lw=1.5, label=v["cam"].name)
                rec = {"profile": [round(float(x), 5) for x in _curves(v["profile"], row, r_json)[0]]}
                if v["profile"].kind == "table":
                    rec["samples"] = [round(float(x), 5) for x in v["profile"].params[row[0]]]
                if learned and v["z2d"] is not None:
                    net = kernel.decode(v["z2d"][row], r * r)[0]
                    ax.plot(r.numpy(), net.numpy(), color=col, lw=0.8, ls="--")
                    rec["phi_dec"] = [round(float(x), 5) for x in kernel.decode(v["z2d"][row], r_json * r_json)[0]]
            entry["views"][v["cam"].name] = rec
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.05)
        ax.set_xlabel("r")
        ax.set_title(f"primitive {g}", fontsize=9)
        if j == 0:
            ax.set_ylabel("d(r)")
        prim_json.append(entry)
    if chosen:
        fig.axes[0].legend(fontsize=6, loc="lower left")
    fig.suptitle(f"{kernel.name} kernel: profiles across views"
                 + (" (solid: drawn, dashed: Phi_dec)" if learned else ""), fontsize=10)
    profiles_png = out / "profiles.png"
    fig.savefig(profiles_png, dpi=120)

    # ---- figure: d1 histograms per view (paper Figs. 5-6) ----------------------------
    nv = len(per_view)
    rows = 2 if render else 1
    fig = Figure(figsize=(2.6 * nv, 2.4 * rows + 0.4), layout="constrained")
    FigureCanvasAgg(fig)
    bg = torch.tensor(background, dtype=torch.float32)
    renderer = backends.get(backend, "cpu") if render else None
    view_json = []
    edges = np.linspace(0.0, 1.0, HIST_BINS + 1)
    for i, v in enumerate(per_view):
        cam = v["cam"]
        d1 = v["d1"].numpy()
        counts, _ = np.histogram(np.clip(d1, 0.0, 1.0), bins=edges)
        if render:
            ax = fig.add_subplot(rows, nv, i + 1)
            with torch.no_grad():
                img = model.render(cam, bg, backend=renderer).image.clamp(0, 1).numpy()
            ax.imshow(img)
            ax.set_axis_off()
            ax.set_title(cam.name, fontsize=8)
        ax = fig.add_subplot(rows, nv, i + 1 + (nv if render else 0))
        ax.hist(np.clip(d1, 0.0, 1.0), bins=edges, color="0.35")
        if len(d1):
            ax.axvline(float(d1.mean()), color="red", ls=":", lw=1.5)
        ax.set_xlim(0, 1)
        ax.set_yticks([])
        ax.set_xlabel("d1", fontsize=8)
        if not render:
            ax.set_title(cam.name, fontsize=8)
        with torch.no_grad():
            mean_profile = (_curves(v["profile"], torch.arange(len(v["idx"])), r_json).mean(0)
                            if len(v["idx"]) else torch.zeros(JSON_POINTS))
        view_json.append({
            "view": cam.name,
            "num_visible": int(len(v["idx"])),
            "d1": {
                "mean": float(d1.mean()) if len(d1) else None,
                "std": float(d1.std()) if len(d1) else None,
                "min": float(d1.min()) if len(d1) else None,
                "max": float(d1.max()) if len(d1) else None,
                "hist_counts": counts.tolist(),
            },
            "mean_profile": [round(float(x), 5) for x in mean_profile],
        })
    fig.suptitle(f"{kernel.name} kernel: d1 = d(r=0) of the visible primitives per view "
                 "(red dotted: mean)", fontsize=10)
    hist_png = out / "d1_histograms.png"
    fig.savefig(hist_png, dpi=120)

    factor = kernel.gaussian_scale_factor({k: v.detach() for k, v in model.prims.items()})
    factor = torch.as_tensor(factor, dtype=torch.float32).flatten()
    doc = {
        "run": str(run),
        "kernel": kernel.name,
        "kernel_options": meta["spec"].get("kernel_options", {}),
        "support_sigmas": kernel.support_sigmas,
        "profile_kind": per_view[0]["profile"].kind if per_view else None,
        "num_primitives": n,
        "views_source": source,
        "radii": [round(float(x), 5) for x in r_json],
        "hist_edges": edges.round(5).tolist(),
        "views": view_json,
        "primitives": prim_json,
        "gaussian_scale_factor": {
            "mean": float(factor.mean()), "median": float(factor.median()),
            "min": float(factor.min()), "max": float(factor.max()),
        },
        "files": [profiles_png.name, hist_png.name],
    }
    (out / "kernels.json").write_text(json.dumps(doc, indent=2) + "\n")
    return out
