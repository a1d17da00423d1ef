"""`splatk bench`: a grid of methods over scenes, each run = fit + eval, then charts.

Layout of OUT::

    OUT/runs/<scene>/<method-id>/         the run folders (`splatk fit` layout + metrics.json)
    OUT/results/<scene>__<method-id>.json one per finished run: metrics, timings, resolved config
    OUT/charts/psnr_vs_{render_ms,train_seconds,footprint_mb}.{png,svg}
    OUT/stability/...                     the same for `--stability` (:mod:`splatk.bench.stability`)
    OUT/charts/stability_<scene>.{png,svg}

Resumable: a run whose result JSON exists is not touched again; a run folder with a checkpoint
but no finished fit continues with ``run_fit(resume=True)``; a finished fit without a result is
only evaluated. Threads, backend and device are not part of what a run is: a grid stopped on one
machine goes on with other values of them. Charts and the table cover every result in
OUT/results, so shell loops that call `splatk bench` once per scene into the same OUT add up.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
import yaml

from ..data import detect_format, load_scene
from ..errors import InputError
from ..machine import machine_info
from ..stages.evaluate import run_eval
from ..stages.auto_settings import settings_as_run
from ..stages.fit import RESUME_CHANGEABLE, run_fit
from ..stages.fit_config import FitConfig
from .methods import PRETRAIN_KEYS, fit_config_for, method_id, pretraining

RESULT_KEYS = ("psnr", "ssim", "lpips", "train_seconds", "render_ms", "footprint_mb", "num_primitives")


class BenchStopped(Exception):
    """A stop request (SIGTERM, Ctrl-C) ended the bench between or inside runs: finished runs
    keep their results, a fit it stopped keeps its checkpoint (``run``), and the same command
    goes on from there."""

    def __init__(self, run: Path | None):
        self.run = run
        super().__init__(f"bench stopped{f' in {run}' if run else ''}")


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


#: settings that say where and how a run executes, not what it computes: those a `splatk fit
#: --resume` may change, less the run's length (a cell's iterations are part of what it is). A
#: result or a stopped run made with other values is the same cell; a stopped one goes on with
#: the values given now
PLACEMENT_SETTINGS = tuple(k for k in RESUME_CHANGEABLE if k not in ("iters", "time_budget"))


def _without_placement(settings):
    """``settings`` (a flat method spec or a nested FitConfig dict) less its placement keys."""
    if not isinstance(settings, dict):
        return settings
    return {k: _without_placement(v) for k, v in settings.items() if k not in PLACEMENT_SETTINGS}


def _same_settings(run: Path, cfg: FitConfig) -> bool:
    """Whether the run folder was started with ``cfg`` (as the run records it:
    :func:`~splatk.stages.auto_settings.settings_as_run`), placement aside (a stale partial run is started
    over)."""
    try:
        saved = yaml.safe_load((run / "config.yaml").read_text())["settings"]
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        return False
    return _without_placement(_normalise(saved)) == _without_placement(_normalise(cfg.to_dict()))


def _same_run_elsewhere(scene, mid: str, as_run: FitConfig, root: Path) -> dict | None:
    """The finished result of another method of ROOT on ``scene`` whose run has the settings
    ``as_run`` (resolved as the run records them), placement aside; None if there is none."""
    wanted = _without_placement(_normalise(as_run.to_dict()))
    scene_path = str(Path(scene).resolve())
    for path in sorted((root / "results").glob(f"{scene_name(scene)}__*.json")):
        try:
            row = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if (row.get("status") == "ok" and row.get("method") != mid and row.get("scene_path") == scene_path
                and not row.get("same_run_as") and isinstance(row.get("config"), dict)
                and _without_placement(_normalise(row["config"])) == wanted and _fit_finished(Path(row["run"]))):
            return row
    return None


def write_json(path: Path, obj) -> None:
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


def finite(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def run_one(
    scene: str | Path,
    method: dict,
    root: Path,
    cfg: BenchConfig,
    on_event: Callable[[str, dict], None] | None = None,
    extra: dict | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict:
    """Fit + eval one (scene, method) under ``root`` (runs/, results/); returns its result row.

    A finished result is returned as it is, with ``"reused": True``. ``should_stop`` is polled
    between training iterations; once it is true the fit saves its checkpoint and
    :class:`BenchStopped` is raised instead of evaluating a run that did not finish.
    """
    stop_requested = should_stop or (lambda: False)
    sname, mid = scene_name(scene), method_id(method, cfg.defaults)
    result_path = root / "results" / f"{sname}__{mid}.json"
    info = {"scene": sname, "method": mid, "result": str(result_path)}
    spec = _normalise({**cfg.defaults, **method, "scale_schedules": cfg.scale_schedules,
                       **({} if cfg.scale_lrs else {"scale_lrs": False})})
    if result_path.is_file():
        row = json.loads(result_path.read_text())
        if row.get("status") == "ok":
            saved_spec = _without_placement(row.get("spec") or {})
            if saved_spec != _without_placement(spec):
                raise InputError(result_path, f"a result for {mid} exists with other settings "
                                 f"({_diff(saved_spec, _without_placement(spec))})",
                                 "use another --out, give the method a name:, or delete that result")
            if on_event:
                on_event("reuse", info)
            return {**row, "reused": True}
    if stop_requested():
        raise BenchStopped(None)
    method = with_pretrained_weights(method, cfg.defaults, root, on_event)
    fit_cfg, notes = fit_config_for(method, cfg.defaults, cfg.scale_schedules, cfg.scale_lrs)
    if "init" not in spec and not has_points(scene):
        fit_cfg.train.init = "random"  # e.g. NeRF-synthetic: nothing to start from but random points
        notes["init"] = "random (no init given and the scene has no SfM points)"
    run = root / "runs" / sname / mid
    row: dict = {"scene": sname, "scene_path": str(Path(scene).resolve()), "method": mid, **(extra or {})}
    try:
        as_run = settings_as_run(scene, fit_cfg)  # `auto` settings as the run folder records them
        same = _same_settings(run, as_run)
        finished = same and _fit_finished(run)
        # a finished run of another method with these settings beats resuming a partial one
        twin = None if finished else _same_run_elsewhere(scene, mid, as_run, root)
        if twin is not None:
            # another method's finished run is this one (e.g. `k: auto` chose the k of a method
            # beside it): evaluate that run, placed as asked now, instead of training it again
            run, fit_cfg = Path(twin["run"]), as_run
            row["same_run_as"] = twin["method"]
            if on_event:
                on_event("same run", {**info, "as": twin["method"]})
        elif finished:
            if on_event:
                on_event("eval-only", info)
        elif same and (run / "checkpoints" / "last.pt").is_file():
            if on_event:
                on_event("resume", info)
            placement = {k: getattr(fit_cfg, k) for k in PLACEMENT_SETTINGS if k != "nproc"}
            run_fit(scene, run, fit_cfg, resume=True, should_stop=stop_requested, resume_options=placement)
        else:
            if on_event:
                on_event("fit", info)
            run_fit(scene, run, fit_cfg, overwrite=True, config_sources={"bench": "method + defaults"},
                    should_stop=stop_requested)
        if stop_requested():
            raise BenchStopped(run)
        if fit_cfg.threads:
            torch.set_num_threads(fit_cfg.threads)
        metrics = run_eval(run, cfg.metrics, lpips_net=cfg.lpips_net, backend=fit_cfg.backend,
                           device=fit_cfg.device)
    except (InputError, ValueError, RuntimeError) as e:
        row.update({"status": "failed", "error": f"{type(e).__name__}: {e}", "config": fit_cfg.to_dict()})
        write_json(result_path, row)
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
    write_json(result_path, row)
    if on_event:
        on_event("done", {**info, "psnr": row["psnr"], "train_seconds": row["train_seconds"]})
    return row


def with_pretrained_weights(method: dict, defaults: dict, root: Path, on_event=None) -> dict:
    """``method`` with ``pretrain: TARGET`` replaced by the weights file it asks for, pretrained
    once per (target, network shape, steps) under ROOT/pretrain/ (resumable like the runs)."""
    from ..stages.pretrain import run_pretrain

    request = pretraining({**defaults, **method})
    if request is None:
        return method
    target, shape, steps = request
    key = hashlib.sha1(json.dumps([target, shape, steps], sort_keys=True).encode()).hexdigest()[:8]
    path = root / "pretrain" / f"{target}-{key}.pt"
    if not path.is_file():
        if on_event:
            on_event("pretrain", {"scene": "-", "method": f"{target} {shape or 'default shape'}", "result": str(path)})
        run_pretrain(target, path, steps=steps, kernel_options=shape, overwrite=True)
    return {**{k: v for k, v in method.items() if k not in PRETRAIN_KEYS}, "weights": str(path.resolve())}


def has_points(scene) -> bool:
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
    should_stop: Callable[[], bool] | None = None,
) -> BenchResult:
    """Run every (scene, method) not finished yet, then chart all results in OUT/results.

    Returns every result row in OUT/results (this call's and earlier ones) and the chart paths.
    """
    from .charts import draw_pareto_charts

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
            run_one(scene, m, out, cfg, on_event, should_stop=should_stop)
    rows = load_results(out / "results")
    paths = draw_pareto_charts(rows, out / "charts") if charts else []
    return BenchResult(rows, paths, out)


def table_rows(rows: list[dict]) -> list[dict]:
    """The printed table: one dict per run with the chart quantities."""
    return [{"scene": r.get("scene"), "method": r.get("method"), "status": r.get("status"),
             **{k: r.get(k) for k in RESULT_KEYS}} for r in rows]
