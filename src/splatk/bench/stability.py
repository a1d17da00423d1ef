"""The stability matrix of `splatk bench --stability`: kernels x conditions per scene, each
cell a bench run, flagged when it ends below its start, rolls back after a NaN, or falls far
below the best kernel under the same condition.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

from ..train.trainer import TrainConfig
from .methods import method_id
from .runner import BenchConfig, BenchResult, finite, has_points, write_json, check_scenes, run_one, scene_name


#: rows: kernels (label -> method settings)
STABILITY_KERNELS: dict[str, dict] = {
    "gaussian": {"kernel": "gaussian"},
    "beta": {"kernel": "beta"},
    "learned-k2": {"kernel": "learned", "k": 2},
    "learned-k4": {"kernel": "learned", "k": 4},
    "learned-k8": {"kernel": "learned", "k": 8},
    "learned-k8-nopre": {"kernel": "learned", "k": 8, "weights": "none"},
}
#: columns: conditions (label -> settings; budget_factor multiplies the base budget)
STABILITY_CONDITIONS: dict[str, dict] = {
    "sfm-init": {"init": "sfm"},
    "random-init": {"init": "random"},
    "quarter-views": {"view_stride": 4},
    "lr-x10": {"lr_scale": 10.0},
    "tiny-budget": {"budget_factor": 0.1},
}
#: a run this far (dB) below the best kernel under the same condition counts as collapsed
COLLAPSE_DB = 3.0


def classify(initial_psnr, final_psnr, nan_rollbacks: int) -> dict:
    """Flags of one stability run: ``below_initial`` (ended below its own starting test PSNR),
    ``diverged`` (below initial, or no finite final PSNR), ``nan`` (rolled back at least once)."""
    final = finite(final_psnr)
    init = finite(initial_psnr)
    below = final is not None and init is not None and final < init
    return {"below_initial": below, "diverged": below or final is None, "nan": nan_rollbacks > 0}


def stability_methods(base: dict, kernels: dict, conditions: dict, scene_has_points: bool
                      ) -> list[tuple[str, str, dict | None, str]]:
    """(row, col, method or None if not applicable, note) for every cell."""
    cells = []
    base_init = base.get("init") or ("sfm" if scene_has_points else "random")
    for row, kspec in kernels.items():
        for col, cspec in conditions.items():
            m = {**base, "init": base_init, **kspec}
            c = dict(cspec)
            factor = c.pop("budget_factor", None)
            m.update(c)
            if factor is not None:
                m["budget"] = max(1, int(int(float(m.get("budget", TrainConfig.budget))) * factor))
            m["name"] = f"{row}__{col}"
            if m.get("init") == "sfm" and not scene_has_points:
                cells.append((row, col, None, "scene has no SfM points"))
            else:
                cells.append((row, col, m, ""))
    return cells


def run_stability(
    scenes: list,
    cfg: BenchConfig,
    out: str | Path,
    kernels: dict | None = None,
    conditions: dict | None = None,
    on_event: Callable[[str, dict], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> BenchResult:
    """The stability matrix: kernels x conditions per scene, into OUT/stability/.

    Writes OUT/stability/results/<scene>__<row>__<col>.json per cell,
    OUT/stability/matrix_<scene>.json (every cell's flags and PSNRs) and the heat map
    OUT/charts/stability_<scene>.{png,svg}. ``cfg.defaults`` is the base of every cell.
    ``should_stop``: as for :func:`~.runner.run_one` (a stopped matrix is finished by the same call).
    """
    from .charts import draw_stability_heatmap

    out = Path(out)
    root = out / "stability"
    kernels = kernels or STABILITY_KERNELS
    conditions = conditions or STABILITY_CONDITIONS
    scenes = check_scenes(scenes)
    all_rows, paths = [], []
    for scene in scenes:
        scene_has_points = has_points(scene)
        sname = scene_name(scene)
        cells = []
        for row, col, m, note in stability_methods(cfg.defaults, kernels, conditions, scene_has_points):
            extra = {"row": row, "col": col}
            if m is None:
                r = {"scene": sname, "method": f"{row}__{col}", "status": "not_applicable", "note": note, **extra}
                write_json(root / "results" / f"{sname}__{row}__{col}.json", r)
            else:
                # fit's defaults, short-run LR boost included, so the matrix tests what a user runs
                sub = BenchConfig(methods=[m], defaults={}, metrics=cfg.metrics, lpips_net=cfg.lpips_net,
                                  scale_schedules=cfg.scale_schedules, scale_lrs=cfg.scale_lrs)
                r = run_one(scene, m, root, sub, on_event, extra, should_stop=should_stop)
                if r.get("status") == "ok":
                    r.update(classify(r.get("initial_psnr"), r.get("psnr"), r.get("nan_rollbacks", 0)))
                    write_json(root / "results" / f"{sname}__{method_id(m)}.json",
                                {k: v for k, v in r.items() if k != "reused"})
            cells.append(r)
        best = {}
        for r in cells:
            p = finite(r.get("psnr"))
            if p is not None:
                best[r["col"]] = max(best.get(r["col"], -math.inf), p)
        for r in cells:
            p = finite(r.get("psnr"))
            r["collapsed"] = p is not None and best.get(r["col"], p) - p > COLLAPSE_DB
        matrix = {
            "scene": sname,
            "rows": list(kernels),
            "cols": list(conditions),
            "kernels": kernels,
            "conditions": conditions,
            "base": cfg.defaults,
            "collapse_db": COLLAPSE_DB,
            "cells": [{k: r.get(k) for k in ("row", "col", "status", "note", "psnr", "initial_psnr",
                                             "nan_rollbacks", "loss_rollbacks", "below_initial",
                                             "diverged", "nan",
                                             "collapsed", "train_seconds", "num_primitives", "error",
                                             "threads")}
                      for r in cells],
        }
        write_json(root / f"matrix_{sname}.json", matrix)
        paths += draw_stability_heatmap(matrix, out / "charts" / f"stability_{sname}")
        all_rows += cells
    return BenchResult(all_rows, paths, out)
