"""Charts of `splatk bench`: PSNR against cost with the Pareto front, the stability heat map, and
one kernel's lead over another seed by seed.

Drawn on matplotlib's Agg canvas directly (no pyplot, so no global backend state), each as PNG
and SVG.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: (result key, axis label, file stem) of the three cost axes
COST_AXES = (
    ("render_ms", "render time per view (ms, median)", "psnr_vs_render_ms"),
    ("train_seconds", "training time (s)", "psnr_vs_train_seconds"),
    ("footprint_mb", "model footprint (MB)", "psnr_vs_footprint_mb"),
)


def _ok(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def pareto_front(xs, ys) -> list[bool]:
    """Which points are non-dominated when lower x (cost) and higher y (quality) are better.

    A point is dominated if another one is at least as good on both axes and strictly better on
    one. Points with a missing or non-finite coordinate are never on the front; identical points
    are both on it.
    """
    pts = [(x, y) if _ok(x) and _ok(y) else None for x, y in zip(xs, ys)]
    flags = []
    for i, p in enumerate(pts):
        if p is None:
            flags.append(False)
            continue
        x, y = p
        dominated = any(q is not None and j != i and q[0] <= x and q[1] >= y and (q[0] < x or q[1] > y)
                        for j, q in enumerate(pts))
        flags.append(not dominated)
    return flags


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, stem: Path) -> list[Path]:
    stem.parent.mkdir(parents=True, exist_ok=True)
    png, svg = stem.with_suffix(".png"), stem.with_suffix(".svg")
    fig.savefig(png, dpi=120)
    fig.savefig(svg)
    return [png, svg]


def method_colors(methods: list[str]) -> dict[str, tuple]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if len(methods) <= 10 else "tab20"]
    return {m: cmap(i % cmap.N) for i, m in enumerate(sorted(methods))}


def draw_pareto_charts(rows: list[dict], out_dir: str | Path) -> list[Path]:
    """PSNR vs render time / training time / footprint, one panel per scene, one point per run,
    a colour per method, the Pareto front as a black line through the non-dominated runs."""
    rows = [r for r in rows if r.get("status") == "ok" and _ok(r.get("psnr"))]
    if not rows:
        return []
    out_dir = Path(out_dir)
    scenes = sorted({r["scene"] for r in rows})
    colors = method_colors(sorted({r["method"] for r in rows}))
    ncols = min(3, len(scenes))
    nrows = math.ceil(len(scenes) / ncols)
    paths = []
    for key, label, stem in COST_AXES:
        fig = _figure(4.2 * ncols + 2.4, 3.4 * nrows + 0.5)
        axes = fig.subplots(nrows, ncols, squeeze=False)
        for ax in axes.flat[len(scenes):]:
            ax.set_visible(False)
        for ax, scene in zip(axes.flat, scenes):
            rs = [r for r in rows if r["scene"] == scene and _ok(r.get(key))]
            xs, ys = [r[key] for r in rs], [r["psnr"] for r in rs]
            front = pareto_front(xs, ys)
            for r, x, y in zip(rs, xs, ys):
                ax.scatter([x], [y], color=colors[r["method"]], s=36, zorder=3, label=r["method"])
            fx = sorted((x, y) for x, y, f in zip(xs, ys, front) if f)
            if fx:
                ax.plot([p[0] for p in fx], [p[1] for p in fx], "k--", lw=1.2, zorder=2)
                ax.scatter([p[0] for p in fx], [p[1] for p in fx], s=110, facecolors="none",
                           edgecolors="black", linewidths=1.2, zorder=4)
            pos = [x for x in xs if x > 0]
            if pos and max(pos) / min(pos) > 20:
                ax.set_xscale("log")
            ax.set_title(scene)
            ax.set_xlabel(label)
            ax.set_ylabel("test PSNR (dB)")
            ax.grid(True, alpha=0.3)
        handles = [_dot(colors[m], m) for m in colors] + [_front_handle()]
        fig.legend(handles=handles, loc="outside right center", fontsize=8, frameon=False)
        fig.suptitle(f"PSNR vs {label.split(' (')[0]} (circled + dashed: Pareto front)", fontsize=10)
        paths += _save(fig, out_dir / stem)
    return paths


def _dot(color, label):
    from matplotlib.lines import Line2D

    return Line2D([], [], marker="o", color=color, linestyle="", label=label)


def _front_handle():
    from matplotlib.lines import Line2D

    return Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor="black", color="black",
                  linestyle="--", markersize=9, label="Pareto front")


def draw_stability_heatmap(matrix: dict, stem: str | Path) -> list[Path]:
    """Final test PSNR per (kernel, condition) cell, annotated; rolled-back runs hatched,
    runs that ended below their initial PSNR outlined red, collapsed runs outlined orange."""
    from matplotlib.patches import Rectangle

    rows, cols = matrix["rows"], matrix["cols"]
    cell = {(c["row"], c["col"]): c for c in matrix["cells"]}
    vals = np.full((len(rows), len(cols)), np.nan)
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            v = cell.get((r, c), {}).get("psnr")
            if _ok(v):
                vals[i, j] = v
    fig = _figure(1.5 * len(cols) + 3.0, 0.75 * len(rows) + 2.2)
    ax = fig.add_subplot(1, 1, 1)
    masked = np.ma.masked_invalid(vals)
    import matplotlib

    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="#d9d9d9")
    finite = vals[np.isfinite(vals)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if vmax - vmin < 1e-6:
        vmin, vmax = vmin - 0.5, vmax + 0.5
    im = ax.imshow(masked, cmap=cmap, vmin=vmin, vmax=vmax, aspect="auto")
    fig.colorbar(im, ax=ax, label="final test PSNR (dB)")
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            cl = cell.get((r, c), {})
            status = cl.get("status")
            if status != "ok":
                text = "n/a" if status == "not_applicable" else (status or "missing")
                ax.text(j, i, text, ha="center", va="center", fontsize=8, color="black")
                continue
            v = vals[i, j]
            lines = [f"{v:.2f}" if np.isfinite(v) else "no PSNR"]
            marks = []
            if _ok(cl.get("initial_psnr")):
                marks.append(f"init {cl['initial_psnr']:.1f}")
            if cl.get("nan_rollbacks"):
                marks.append(f"NaN×{cl['nan_rollbacks']}")
            if cl.get("loss_rollbacks"):
                marks.append(f"rollback×{cl['loss_rollbacks']}")
            if cl.get("below_initial"):
                marks.append("↓init")
            lines.append(" ".join(marks))
            light = np.isfinite(v) and (v - vmin) / (vmax - vmin) > 0.6
            ax.text(j, i, "\n".join(lines), ha="center", va="center", fontsize=7.5,
                    color="black" if light else "white")
            if cl.get("nan"):
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///",
                                       edgecolor="white", linewidth=0))
            if cl.get("diverged") or cl.get("below_initial"):
                ax.add_patch(Rectangle((j - 0.47, i - 0.47), 0.94, 0.94, fill=False, edgecolor="red", linewidth=2.5))
            elif cl.get("collapsed"):
                ax.add_patch(Rectangle((j - 0.47, i - 0.47), 0.94, 0.94, fill=False, edgecolor="orange",
                                       linewidth=2.5, linestyle="--"))
    ax.set_xticks(range(len(cols)), cols, rotation=20, ha="right")
    ax.set_yticks(range(len(rows)), rows)
    ax.set_title(f"stability: {matrix['scene']}", fontsize=10)
    ax.set_xlabel("hatched: NaN rollback(s); red box: ended below its initial PSNR (diverged);\n"
                  f"orange dashed: > {matrix.get('collapse_db', 3):g} dB below the best kernel of its "
                  "column; grey: not run", fontsize=7)
    return _save(fig, Path(stem))


def draw_seed_gaps(doc: dict, stem: str | Path) -> list[Path]:
    """Each (scene, kernel) row of an over-seeds comparison as a line: a dot per seed at that seed's
    test-PSNR difference to the baseline, a black diamond at the mean with its standard error, so
    the seed spread is seen beside the mean it is summed into. Validation rows above tuning rows."""
    rows = [r for r in doc["per_scene"] if r.get("gaps")]
    if not rows:
        return []
    rows = sorted(rows, key=lambda r: r["set"] != "validation")  # stable: keeps the scenes' order
    colors = {"validation": "tab:blue", "tuning": "tab:orange"}
    fig = _figure(7.5, 0.42 * len(rows) + 1.6)
    ax = fig.add_subplot(1, 1, 1)
    for y, r in enumerate(rows):
        ax.scatter(r["gaps"], [y] * len(r["gaps"]), s=22, color=colors.get(r["set"], "grey"), alpha=0.6,
                   zorder=3)
        ax.errorbar([r["gap_mean"]], [y], xerr=[r["gap_standard_error"] or 0.0], fmt="D", color="black",
                    markersize=6, capsize=3, zorder=4)
    ax.axvline(0.0, color="black", lw=0.8)
    ax.set_yticks(range(len(rows)), [f"{r['scene']} · {r['kernel']} ({len(r['gaps'])})" for r in rows],
                  fontsize=8)
    ax.invert_yaxis()
    ax.grid(True, axis="x", alpha=0.3)
    ax.set_xlabel(f"test PSNR − {doc['baseline']} (dB); a dot per seed (seeds in brackets), "
                  "diamond: mean ± standard error", fontsize=8)
    handles = [_dot(c, name) for name, c in colors.items() if any(r["set"] == name for r in rows)]
    ax.legend(handles=handles, fontsize=8, loc="best")
    ax.set_title(f"protocol {doc['protocol']}: each kernel against {doc['baseline']}, seed by seed", fontsize=10)
    return _save(fig, Path(stem))
