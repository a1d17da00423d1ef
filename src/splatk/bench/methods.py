"""The method grammar of `splatk bench`: methods as dicts of fit settings, grids of them,
their ids (file names of results), and bench files.

A method is a dict of fit settings (see :func:`fit_config_for`)::

    {kernel: learned, k: 4, weights: none, color: sh, budget: 30000 | auto,
     budget_bytes: 4MB, iters: 3000, time_budget: 600, name: my-id, ...FitConfig/TrainConfig fields}

``pretrain: TARGET`` (cosine, gaussian, polynomial, linear; with ``pretrain_steps``) makes the
bench pretrain the learned kernel's networks for the method's network shape (its
``kernel_options``) once, under OUT/pretrain/, and fit with them (paper Tab. 3-5).

``primitive: planar`` fits 2D surfels (:class:`~splatk.models.planar.PlanarModel`) with the
planar kernel of that name; ``k`` is volumetric-only and is ignored there.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import re
from pathlib import Path


from ..errors import InputError
from ..kernels.auto_k import AUTO_K
from ..stages.fit_config import FitConfig, check_fit_config, fit_config_from_options, parse_bytes
from ..yaml_files import read_yaml_file

#: keys a method may have besides FitConfig / TrainConfig fields
METHOD_KEYS = ("name", "k", "weights", "budget_bytes", "kernel_options", "pretrain", "pretrain_steps")
#: the method keys :func:`pretraining` reads (the bench turns them into ``weights``)
PRETRAIN_KEYS = ("pretrain", "pretrain_steps")


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
            parts.append(f"k{m.pop('k', AUTO_K)}")
        if "pretrain" in m:
            parts.append(f"pre{m.pop('pretrain')}")
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
    if pretraining(spec) is not None:
        # checked as a method without pretrained networks; the runner fits with the pretrained file
        spec = {k: v for k, v in spec.items() if k not in PRETRAIN_KEYS}
        spec.setdefault("weights", "none")
    # the bench's switches, unless the method sets its own; the translator scales short runs
    # as it does for `splatk fit` (settings the method gives stay as given)
    options = {"scale_schedules": scale_schedules, "short_run_lrs": scale_lrs, **spec}
    cfg, notes = fit_config_from_options(options, {k: "bench method" for k in options})
    check_fit_config(cfg, "bench method")
    return cfg, notes


def pretraining(method: dict) -> tuple[str, dict, int | None] | None:
    """(target, network shape, steps) a method asks the bench to pretrain, or None."""
    if "pretrain" not in method:
        return None
    from ..kernels.learned import ARCH_OPTIONS
    from ..stages.pretrain import TARGETS

    target = method["pretrain"]
    if method.get("kernel") != "learned" or method.get("primitive", "volumetric") != "volumetric":
        raise InputError(None, f"pretrain: {target!r} is for the volumetric learned kernel",
                         "drop pretrain from the other methods")
    if target not in TARGETS:
        raise InputError(None, f"pretrain: {target!r} is not a target", f"use one of {', '.join(TARGETS)}")
    shape = {k: v for k, v in (method.get("kernel_options") or {}).items() if k in ARCH_OPTIONS}
    steps = method.get("pretrain_steps")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise InputError(None, f"pretrain_steps: {steps!r} is not a positive whole number", "e.g. pretrain_steps: 2000")
    return target, shape, steps


def load_bench_file(path: str | Path) -> dict:
    """A bench YAML: ``defaults``, ``methods`` and/or ``grid``, optional ``scenes``,
    ``metrics``, ``lpips_net``, ``scale_schedules``, a ``stability`` section and a ``protocol``
    (a published protocol's name and the settings that make it that protocol, e.g.
    ``{name: paper Tab. 2, iters: 30000}``: :func:`protocol_departures` names what a run changes)."""
    path = Path(path)
    data = read_yaml_file(path, "bench file") or {}
    if not isinstance(data, dict):
        raise InputError(path, "a bench file is a mapping (defaults, methods, grid, scenes, stability)")
    known = {"defaults", "methods", "grid", "scenes", "metrics", "lpips_net", "scale_schedules", "stability",
             "protocol"}
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


def protocol_departures(data: dict, defaults: dict, scale_schedules: bool) -> list[str]:
    """The settings of a bench that depart from its file's ``protocol`` (empty: it runs the
    protocol as published)."""
    protocol = data.get("protocol") or {}
    out = []
    for key, value in protocol.items():
        if key == "name":
            continue
        if key == "scale_schedules":
            if bool(scale_schedules) != bool(value):
                out.append(f"scale_schedules {scale_schedules} (protocol: {value})")
        elif defaults.get(key, value) != value:
            out.append(f"{key} {defaults.get(key)} (protocol: {value})")
    if protocol and defaults.get("time_budget") is not None:
        out.append(f"time_budget {defaults['time_budget']} (protocol: none)")
    return out
