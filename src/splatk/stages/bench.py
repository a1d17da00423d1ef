"""`splatk bench`: a grid of methods over scenes, each run = fit + eval, then charts.

Layout of OUT::

    OUT/runs/<scene>/<method-id>/         the run folders (`splatk fit` layout + metrics.json)
    OUT/results/<scene>__<method-id>.json one per finished run: metrics, timings, resolved config
    OUT/charts/psnr_vs_{render_ms,train_seconds,footprint_mb}.{png,svg}
    OUT/stability/...                     the same for `--stability` (see :func:`run_stability`)
    OUT/charts/stability_<scene>.{png,svg}

Resumable: a run whose result JSON exists is not touched again; a run folder with a checkpoint
but no finished fit continues with ``run_fit(resume=True)``; a finished fit without a result is
only evaluated. Charts and the table cover every result in OUT/results, so shell loops that call
`splatk bench` once per scene into the same OUT add up.

A method is a dict of fit settings (see :func:`fit_config_for`)::

    {kernel: learned, k: 4, weights: none, color: sh, budget: 30000 | auto,
     budget_bytes: 4MB, iters: 3000, time_budget: 600, name: my-id, ...FitConfig/TrainConfig fields}

``primitive: planar`` fits 2D surfels (:class:`~splatk.models.planar.PlanarModel`) with the
planar kernel of that name; ``k`` is volumetric-only and is ignored there.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
import yaml

from ..data import detect_format, load_scene
from ..errors import InputError
from ..machine import machine_info
from ..train.trainer import TrainConfig
from .evaluate import run_eval
from .fit import FULL_ITERS, boost_short_run_lrs, run_fit, scale_schedules_to_run
from .fit_config import FitConfig, check_fit_config, fit_config_from_options, parse_bytes

#: keys a method may have besides FitConfig / TrainConfig fields
METHOD_KEYS = ("name", "k", "weights", "budget_bytes", "kernel_options")
RESULT_KEYS = ("psnr", "ssim", "lpips", "train_seconds", "render_ms", "footprint_mb", "num_primitives")



@dataclass
class BenchConfig:
    """What `splatk bench` runs: methods x scenes, with shared defaults."""

    #: one dict per method (see the module docstring)
    methods: list[dict] = field(default_factory=list)
    #: settings every method starts from (its own keys win)
    defaults: dict = field(default_factory=dict)
    #: metrics for `eval`
    metrics: tuple[str, ...] = ("psnr", "ssim", "lpips")
    #: LPIPS network: alex | vgg
    lpips_net: str = "alex"
    #: runs shorter than 30k iterations get the paper's schedules scaled to their length:
    #: refine_start, refine_every, sh_degree_interval and the learned kernel's freeze_iters,
    #: and the learning rates tuned for 30k iterations raised (log-scales, the learned
    #: kernel's latents and networks)
    scale_schedules: bool = True
    #: with scale_schedules, also raise the LRs tuned for 30k iterations, as `splatk fit` does
    #: by default (the kernel grid and the stability matrix both run so)
    scale_lrs: bool = True


# ---- methods ------------------------------------------------------------------------------
def expand_grid(grid: dict) -> list[dict]:
    """Cartesian product of ``{key: [values]}``; a dict value is merged into the method instead
    of being assigned to the key (``kernel: [gaussian, {kernel: learned, k: 4}]``)."""
    keys = list(grid)
    lists = [v if isinstance(v, list) else [v] for v in grid.values()]
    methods = []
    for combo in itertools.product(*lists):
        m: dict = {}
        for key, value in zip(keys, combo):
            if isinstance(value, dict):
                m.update(value)
            else:
                m[key] = value
        methods.append(m)
    return methods


def method_id(method: dict, defaults: dict | None = None) -> str:
    """A readable, file-name-safe id that changes whenever the method's settings do.

    Of ``defaults`` (the bench's shared settings) only the primitive type counts: a preset may
    set ``primitive: planar`` for every method, and a planar result must never take the file
    name of a volumetric one (ids of planar runs start with ``planar-``).
    """
    if method.get("name"):
        return re.sub(r"[^A-Za-z0-9._+-]", "_", str(method["name"]))
    m = dict(method)
    kernel = m.pop("kernel", "gaussian")
    planar = m.pop("primitive", (defaults or {}).get("primitive", "volumetric")) == "planar"
    # a planar run never shares an id (and so a result file) with a volumetric one
    parts = ["planar", kernel] if planar else [kernel]
    if planar:
        m.pop("k", None)  # volumetric-only (fit_config_for ignores it too)
    if kernel == "learned":
        if not planar:
            parts.append(f"k{m.pop('k', 2)}")
        w = m.pop("weights", None)
        if w is not None and str(w).lower() == "none":
            parts.append("nopre")
        elif w is not None:
            parts.append("w" + _short_hash(w))
    else:
        m.pop("k", None)
        m.pop("weights", None)
    parts.append(m.pop("color", "sh"))
    if "budget_bytes" in m:
        parts.append(f"B{_human_bytes(parse_bytes(m.pop('budget_bytes')))}")
        m.pop("budget", None)
    elif "budget" in m:
        b = m.pop("budget")
        parts.append("bauto" if str(b).lower() == "auto" else f"b{int(float(b))}")
    if "iters" in m:
        parts.append(f"i{int(m.pop('iters'))}")
    if m.get("time_budget") is not None:
        parts.append(f"t{_num(m.pop('time_budget'))}s")
    m.pop("time_budget", None)
    if m:
        parts.append(_short_hash(m))
    return "-".join(parts)


def _short_hash(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:6]


def _num(x) -> str:
    x = float(x)
    return str(int(x)) if x == int(x) else f"{x:g}"


def _human_bytes(n: int) -> str:
    for unit, size in (("G", 2**30), ("M", 2**20), ("K", 2**10)):
        if n >= size and n % (size // 16 or 1) == 0:
            return f"{_num(n / size)}{unit}"
    return str(n)


def fit_config_for(method: dict, defaults: dict | None = None, scale_schedules: bool = True,
                   scale_lrs: bool = True) -> tuple[FitConfig, dict]:
    """Resolve a method (over ``defaults``) into a checked FitConfig, as `splatk fit` would
    with the same options (:func:`~splatk.stages.fit_config.fit_config_from_options`).

    Returns (config, notes): notes say how the budget and schedules were derived.
    """
    spec = {**(defaults or {}), **method}
    if "budget_bytes" in method:
        spec.pop("budget", None)  # the method's byte budget beats a default count
    cfg, notes = fit_config_from_options(spec, {k: "bench method" for k in spec})
    check_fit_config(cfg, "bench method")
    if scale_schedules and cfg.train.time_budget is None and cfg.train.iters < FULL_ITERS:
        s = cfg.train.iters / FULL_ITERS
        scaled = scale_schedules_to_run(cfg, keep=set(spec))  # as `splatk fit` does
        if scale_lrs:  # as `splatk fit --short-run-lrs` does
            scaled.update(boost_short_run_lrs(cfg, keep=set(spec)))
        if scaled:
            notes["scaled_schedules"] = {"factor": s, **scaled}
    return cfg, notes


def load_bench_file(path: str | Path) -> dict:
    """A bench YAML: ``defaults``, ``methods`` and/or ``grid``, optional ``scenes``,
    ``metrics``, ``lpips_net``, ``scale_schedules`` and a ``stability`` section."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise InputError(path, f"invalid YAML ({e})") from e
    if not isinstance(data, dict):
        raise InputError(path, "a bench file is a mapping (defaults, methods, grid, scenes, stability)")
    known = {"defaults", "methods", "grid", "scenes", "metrics", "lpips_net", "scale_schedules", "stability"}
    unknown = set(data) - known
    if unknown:
        raise InputError(path, f"unknown keys {', '.join(sorted(unknown))}", f"use {', '.join(sorted(known))}")
    methods = list(data.get("methods") or [])
    if data.get("grid"):
        methods += expand_grid(data["grid"])
    data["methods"] = methods
    if data.get("scenes"):
        data["scenes"] = [str((path.parent / s) if not Path(s).is_absolute() else s) for s in data["scenes"]]
    return data


# ---- one run --------------------------------------------------------------------------------
def scene_name(scene: str | Path) -> str:
    p = Path(scene).resolve()
    return p.parent.name if p.is_file() else p.name


def _fit_finished(run: Path) -> bool:
    """model.pt and fit.json written, and the run did not stop early."""
    if not ((run / "model.pt").is_file() and (run / "fit.json").is_file() and (run / "config.yaml").is_file()):
        return False
    summary = json.loads((run / "fit.json").read_text())
    t = yaml.safe_load((run / "config.yaml").read_text())["settings"]["train"]
    if t.get("time_budget"):
        return summary["train_seconds"] >= t["time_budget"] or summary["iterations"] >= t["iters"]
    return summary["iterations"] >= t["iters"]


def _normalise(obj):
    """JSON round trip: the form a spec has when read back from a result file."""
    return json.loads(json.dumps(obj, sort_keys=True, default=str))


def _diff(a: dict, b: dict) -> str:
    keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return ", ".join(f"{k}: {a.get(k)!r} there, {b.get(k)!r} now" for k in keys) or "?"


def _same_settings(run: Path, cfg: FitConfig) -> bool:
    """Whether the run folder was started with ``cfg`` (a stale partial run is started over)."""
    try:
        saved = yaml.safe_load((run / "config.yaml").read_text())["settings"]
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        return False
    return _normalise(saved) == _normalise(cfg.to_dict())


def _write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=_json_default))
    os.replace(tmp, path)


def _json_default(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def _finite(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def run_one(
    scene: str | Path,
    method: dict,
    root: Path,
    cfg: BenchConfig,
    on_event: Callable[[str, dict], None] | None = None,
    extra: dict | None = None,
) -> dict:
    """Fit + eval one (scene, method) under ``root`` (runs/, results/); returns its result row.

    A finished result is returned as it is, with ``"reused": True``.
    """
    sname, mid = scene_name(scene), method_id(method, cfg.defaults)
    result_path = root / "results" / f"{sname}__{mid}.json"
    info = {"scene": sname, "method": mid, "result": str(result_path)}
    spec = _normalise({**cfg.defaults, **method, "scale_schedules": cfg.scale_schedules,
                       **({} if cfg.scale_lrs else {"scale_lrs": False})})
    if result_path.is_file():
        row = json.loads(result_path.read_text())
        if row.get("status") == "ok":
            if row.get("spec") != spec:
                raise InputError(result_path, f"a result for {mid} exists with other settings "
                                 f"({_diff(row.get('spec') or {}, spec)})",
                                 "use another --out, give the method a name:, or delete that result")
            if on_event:
                on_event("reuse", info)
            return {**row, "reused": True}
    fit_cfg, notes = fit_config_for(method, cfg.defaults, cfg.scale_schedules, cfg.scale_lrs)
    if "init" not in spec and not _has_points(scene):
        fit_cfg.train.init = "random"  # e.g. NeRF-synthetic: nothing to start from but random points
        notes["init"] = "random (no init given and the scene has no SfM points)"
    run = root / "runs" / sname / mid
    row: dict = {"scene": sname, "scene_path": str(Path(scene).resolve()), "method": mid, **(extra or {})}
    same = _same_settings(run, fit_cfg)
    try:
        if same and _fit_finished(run):
            if on_event:
                on_event("eval-only", info)
        elif same and (run / "checkpoints" / "last.pt").is_file():
            if on_event:
                on_event("resume", info)
            run_fit(scene, run, fit_cfg, resume=True)
        else:
            if on_event:
                on_event("fit", info)
            run_fit(scene, run, fit_cfg, overwrite=True, config_sources={"bench": "method + defaults"})
        if fit_cfg.threads:
            torch.set_num_threads(fit_cfg.threads)
        metrics = run_eval(run, cfg.metrics, lpips_net=cfg.lpips_net, backend=fit_cfg.backend)
    except (InputError, ValueError, RuntimeError) as e:
        row.update({"status": "failed", "error": f"{type(e).__name__}: {e}", "config": fit_cfg.to_dict()})
        _write_json(result_path, row)
        if on_event:
            on_event("failed", {**info, "error": row["error"]})
        return row
    summary = json.loads((run / "fit.json").read_text())
    events = summary.get("events", [])
    row.update({
        "status": "ok",
        "psnr": metrics["mean"].get("psnr"),
        "ssim": metrics["mean"].get("ssim"),
        "lpips": metrics["mean"].get("lpips"),
        "train_seconds": summary["train_seconds"],
        "render_ms": metrics["render_ms"],
        "footprint_mb": metrics["footprint_mb"],
        "num_primitives": metrics["num_primitives"],
        "iterations": summary["iterations"],
        "initial_psnr": summary.get("initial_psnr"),
        "nan_rollbacks": sum(1 for e in events if e.get("event") == "nan_rollback"),
        "loss_rollbacks": sum(1 for e in events if e.get("event") == "loss_rollback"),
        "events": events,
        "threads": metrics["threads"],
        "backend": metrics["backend"],
        "lpips_net": metrics["lpips_net"],
        "test_views": metrics["num_views"],
        "warnings": metrics["warnings"],
        "method_spec": method,
        "spec": spec,
        "derived": notes,
        "config": fit_cfg.to_dict(),
        "run": str(run),
        "machine": machine_info(),
    })
    if summary.get("auto_budget"):
        row["auto_budget"] = summary["auto_budget"]["chosen_budget"]
        # the whole report (stages, gains, pruning) too: the run folder may be deleted
        row["auto_budget_report"] = summary["auto_budget"]
    _write_json(result_path, row)
    if on_event:
        on_event("done", {**info, "psnr": row["psnr"], "train_seconds": row["train_seconds"]})
    return row


def _has_points(scene) -> bool:
    return load_scene(scene, load_images=False).points.shape[0] > 0


def check_scenes(scenes: list) -> list[str]:
    if not scenes:
        raise InputError(None, "no scenes given", "pass scene folders, or list them under scenes: in the bench file")
    names: dict[str, str] = {}
    for s in scenes:
        detect_format(s)  # raises InputError naming the folder
        n = scene_name(s)
        if n in names and names[n] != str(Path(s).resolve()):
            raise InputError(s, f"two scenes are both called {n!r}", "results are named by scene folder name")
        names[n] = str(Path(s).resolve())
    return [str(s) for s in scenes]


def load_results(results_dir: Path) -> list[dict]:
    rows = []
    for p in sorted(Path(results_dir).glob("*.json")):
        try:
            rows.append(json.loads(p.read_text()))
        except json.JSONDecodeError:
            continue
    return sorted(rows, key=lambda r: (r.get("scene", ""), r.get("method", "")))


@dataclass
class BenchResult:
    rows: list[dict]
    charts: list[Path]
    out: Path


def run_bench(
    scenes: list,
    cfg: BenchConfig,
    out: str | Path,
    on_event: Callable[[str, dict], None] | None = None,
    charts: bool = True,
) -> BenchResult:
    """Run every (scene, method) not finished yet, then chart all results in OUT/results.

    Returns every result row in OUT/results (this call's and earlier ones) and the chart paths.
    """
    from .bench_charts import draw_pareto_charts

    out = Path(out)
    if not cfg.methods:
        raise InputError(None, "no methods given", "pass --kernel/--budget flags or a bench YAML with methods")
    scenes = check_scenes(scenes)
    ids = [method_id(m, cfg.defaults) for m in cfg.methods]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise InputError(None, f"methods with the same id: {', '.join(sorted(dup))}", "give them a name:")
    for m in cfg.methods:
        fit_config_for(m, cfg.defaults, cfg.scale_schedules, cfg.scale_lrs)  # fail on bad settings before any training
    for scene in scenes:
        for m in cfg.methods:
            run_one(scene, m, out, cfg, on_event)
    rows = load_results(out / "results")
    paths = draw_pareto_charts(rows, out / "charts") if charts else []
    return BenchResult(rows, paths, out)


def table_rows(rows: list[dict]) -> list[dict]:
    """The printed table: one dict per run with the chart quantities."""
    return [{"scene": r.get("scene"), "method": r.get("method"), "status": r.get("status"),
             **{k: r.get(k) for k in RESULT_KEYS}} for r in rows]


# ---- stability matrix -----------------------------------------------------------------------
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
    final = _finite(final_psnr)
    init = _finite(initial_psnr)
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
) -> BenchResult:
    """The stability matrix: kernels x conditions per scene, into OUT/stability/.

    Writes OUT/stability/results/<scene>__<row>__<col>.json per cell,
    OUT/stability/matrix_<scene>.json (every cell's flags and PSNRs) and the heat map
    OUT/charts/stability_<scene>.{png,svg}. ``cfg.defaults`` is the base of every cell.
    """
    from .bench_charts import draw_stability_heatmap

    out = Path(out)
    root = out / "stability"
    kernels = kernels or STABILITY_KERNELS
    conditions = conditions or STABILITY_CONDITIONS
    scenes = check_scenes(scenes)
    all_rows, paths = [], []
    for scene in scenes:
        has_points = _has_points(scene)
        sname = scene_name(scene)
        cells = []
        for row, col, m, note in stability_methods(cfg.defaults, kernels, conditions, has_points):
            extra = {"row": row, "col": col}
            if m is None:
                r = {"scene": sname, "method": f"{row}__{col}", "status": "not_applicable", "note": note, **extra}
                _write_json(root / "results" / f"{sname}__{row}__{col}.json", r)
            else:
                # fit's defaults, short-run LR boost included, so the matrix tests what a user runs
                sub = BenchConfig(methods=[m], defaults={}, metrics=cfg.metrics, lpips_net=cfg.lpips_net,
                                  scale_schedules=cfg.scale_schedules, scale_lrs=cfg.scale_lrs)
                r = run_one(scene, m, root, sub, on_event, extra)
                if r.get("status") == "ok":
                    r.update(classify(r.get("initial_psnr"), r.get("psnr"), r.get("nan_rollbacks", 0)))
                    _write_json(root / "results" / f"{sname}__{method_id(m)}.json",
                                {k: v for k, v in r.items() if k != "reused"})
            cells.append(r)
        best = {}
        for r in cells:
            p = _finite(r.get("psnr"))
            if p is not None:
                best[r["col"]] = max(best.get(r["col"], -math.inf), p)
        for r in cells:
            p = _finite(r.get("psnr"))
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
        _write_json(root / f"matrix_{sname}.json", matrix)
        paths += draw_stability_heatmap(matrix, out / "charts" / f"stability_{sname}")
        all_rows += cells
    return BenchResult(all_rows, paths, out)
