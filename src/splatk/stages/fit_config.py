"""`splatk fit`'s settings: the dataclass, the one translator from flat options, the checks.

Options reach a fit from the command line, the ``SPLATK_*`` environment, a preset, a bench
method or a resumed run's ``config.yaml``. All of them go through :func:`fit_config_from_options`
(flat names as the command line spells them) and every resulting :class:`FitConfig` through
:func:`check_fit_config` before anything is read or written: one schema, one error format, the
same one-line style as the loaders (``splatk: error: --sh-degree 7: must be 0 to 3 (...)``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from ..data import EVAL_SPLITS
from ..errors import InputError
from ..kernels.auto_k import AUTO_K
from ..machine import memory_bytes
from ..option_rules import (BOOL, check_value, choice, float_range, int_range, option_error, parse_bytes,
                            parse_duration, valid)
from ..train.adc import ADCConfig
from ..train.strategies import STRATEGIES
from ..train.trainer import MCMC_FIELDS, TrainConfig
from .autobudget import AutoBudgetConfig
from .fit_memory import bytes_per_primitive, color_options, max_budget, train_bytes_per_primitive
from .fit_ranks import check_processes, process_options
from .run_length import run_fraction, scale_to_run_length

PRIMITIVES = ("volumetric", "planar")


@dataclass
class FitConfig:
    """Everything `splatk fit` can be told. Presets (YAML) and flags fill these fields."""

    #: splatting kernel: gaussian | beta | student_t | learned
    kernel: str = "gaussian"
    #: kernel options (learned: k, latent dims, widths, weights file ...)
    kernel_options: dict = field(default_factory=dict)
    #: colour model: sh (spherical harmonics) | sb (spherical Beta)
    color: str = "sh"
    #: maximum SH degree (raised by one every `sh_degree_interval` iterations)
    sh_degree: int = 3
    #: number of spherical-Beta lobes (color = sb)
    sb_lobes: int = 2
    #: primitive type: volumetric (3D ellipsoids) | planar (2D surfels)
    primitive: str = "volumetric"
    #: image downscale factor
    downscale: float = 1.0
    #: every n-th image is a test view when the dataset names none
    test_every: int = 8
    #: held-out (the test views above) | all (every view trains and is evaluated) | none (every
    #: view trains, none is evaluated)
    eval_split: str = "held-out"
    #: train on every n-th train view only (4: a quarter of them); test views are unaffected
    view_stride: int = 1
    #: background colour for RGBA data and renders (None: the loader's default; `--background
    #: random` keeps that for evaluation and sets train.random_background)
    background: list | None = None
    #: rasteriser backend: auto | torch | cpu
    backend: str = "auto"
    #: torch device
    device: str = "cpu"
    #: torch threads (0: all cores)
    threads: int = 0
    #: training processes (data parallel: each renders its share of the --batch-views views of
    #: a step); under torchrun, the launcher's world size
    nproc: int = 1
    #: checkpoint every n iterations (and on Ctrl-C)
    checkpoint_every: int = 1000
    #: runs shorter than 30k iterations: scale the step-count schedules tuned for 30k to the
    #: run's length (:mod:`splatk.stages.run_length`)
    scale_schedules: bool = True
    #: ... and raise the learning rates tuned for 30k iterations (with scale_schedules only)
    short_run_lrs: bool = True
    #: choose the budget from held-out train views (`--budget auto`); None: use train.budget
    auto_budget: AutoBudgetConfig | None = None
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FitConfig":
        d = dict(d)
        train = TrainConfig.from_dict(d.pop("train", {}))
        if isinstance(d.get("auto_budget"), dict):
            d["auto_budget"] = AutoBudgetConfig.from_dict(d["auto_budget"])
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown fit settings: {', '.join(sorted(unknown))}")
        return cls(train=train, **d)


_FIT_FIELDS = {f.name for f in fields(FitConfig)} - {"train", "auto_budget"}
#: the settings that differ under ``--strategy adc`` unless given: 3DGS's (its train.py and
#: GaussianModel.create_from_pcd / the Blender loader's random init)
ADC_START = {"opacity_reg": 0.0, "scale_reg": 0.0, "init_opacity": 0.1, "init_scale": 1.0, "random_points": 100_000,
             "random_extent": 0.27}

#: ADC's settings with flat names (the others, e.g. its min_opacity, only nested: ``adc: {...}``)
ADC_FLAT = ("densify_from", "densify_until", "densify_every", "opacity_reset_every", "grad_threshold",
            "percent_dense")
#: flat names of TrainConfig fields, its MCMC and ADC settings included (``refine_every``:
#: train.mcmc, ``densify_until``: train.adc); ``adc`` itself takes a mapping
_TRAIN_FIELDS = {f.name for f in fields(TrainConfig)} - {"mcmc"} | set(MCMC_FIELDS) | set(ADC_FLAT)
#: flat option names besides FitConfig / TrainConfig fields
EXTRA_OPTIONS = ("k", "weights", "kernel_weights", "budget_bytes", "kernel_options", "auto_budget", "name")


# ---- values as a user writes them ---------------------------------------------------------------
# ---- the one translator -------------------------------------------------------------------------
def fit_config_from_options(options: dict, sources: dict | None = None,
                            base: FitConfig | None = None) -> tuple[FitConfig, dict]:
    """Flat options (command-line names: ``kernel``, ``k``, ``budget``, ``budget_bytes``,
    ``time_budget``, ``iters``, any FitConfig or TrainConfig field) -> (checked FitConfig, notes).

    ``None`` values mean "not given". ``base`` (default: the defaults) is the config the
    options apply to. A new config (no ``base``) is then scaled to its run length
    (:func:`~splatk.stages.run_length.scale_to_run_length`; given options stay as given).
    ``notes`` say how derived values (the budget from bytes, the scaled schedules) were found.
    Unknown names, unreadable values and values out of range (:func:`check_fit_config`) are
    InputErrors.
    """
    sources = sources or {}
    # None: not given; but a bench method's ``weights: null`` means "no pretrained networks"
    opts = {k.replace("-", "_"): v for k, v in options.items() if v is not None or k == "weights"}
    cfg = FitConfig.from_dict(base.to_dict()) if base is not None else FitConfig()
    notes: dict = {}
    given = set(opts) | set(opts["adc"] if isinstance(opts.get("adc"), dict) else ())
    unknown = sorted(set(opts) - _FIT_FIELDS - _TRAIN_FIELDS - set(EXTRA_OPTIONS))
    if unknown:
        src = sources.get(unknown[0])
        raise InputError(None, f"unknown fit setting {unknown[0]!r}" + (f" (from the {src})" if src else ""),
                         "see `splatk fit --help` for the settings")
    opts.pop("name", None)
    process_options(opts, sources, new_run=base is None)
    kernel_options = dict(cfg.kernel_options)
    if isinstance(opts.get("kernel_options"), dict):
        kernel_options.update(opts.pop("kernel_options"))
    elif "kernel_options" in opts:
        raise option_error("kernel_options", opts["kernel_options"], "must be a mapping", "write kernel_options: {k: 4}",
                            sources.get("kernel_options"))
    for key in ("kernel", "primitive"):
        if key in opts:
            setattr(cfg, key, opts.pop(key))
    planar = cfg.primitive == "planar"
    _check_flags_apply(opts, sources, cfg.kernel, planar, opts.get("color", cfg.color),
                       opts.get("eval_split", cfg.eval_split))
    if "k" in opts:
        k = _read_k(opts.pop("k"), sources)
        if cfg.kernel == "learned" and not planar:  # the planar learned kernel has no k
            kernel_options["k"] = k  # "auto" is resolved when the scene is loaded (resolve_auto_k)
    for key in ("weights", "kernel_weights"):
        if key in opts:
            w = opts.pop(key)
            if cfg.kernel == "learned":
                kernel_options["weights"] = _weights_path(w)
    if cfg.kernel == "learned" and cfg.primitive == "volumetric" and base is None:
        _adopt_network_shape(kernel_options)
        # a new run lets the scene choose k unless told (decision 0105)
        kernel_options.setdefault("k", AUTO_K)
    cfg.kernel_options = kernel_options
    auto_options = opts.pop("auto_budget", None)
    budget_bytes = opts.pop("budget_bytes", None)
    budget = opts.pop("budget", None)
    if "time_budget" in opts:
        raw = opts.pop("time_budget")
        try:
            cfg.train.time_budget = parse_duration(raw)
        except ValueError as e:
            raise option_error("time_budget", raw, str(e).split(" (")[0], "examples: 10m, 90s, 1h30m",
                                sources.get("time_budget")) from None
        if "iters" not in opts and cfg.train.time_budget is not None:
            cfg.train.iters = 10**9  # the clock decides (with iters too, whichever ends first)
    if "adc" in opts:
        nested = opts.pop("adc")
        known = {f.name for f in fields(ADCConfig)}
        if not isinstance(nested, dict) or set(nested) - known:
            raise option_error("adc", nested, f"must be a mapping of {', '.join(sorted(known))}",
                               "e.g. adc: {grad_threshold: 0.0002}", sources.get("adc"))
        for key, value in nested.items():
            setattr(cfg.train.adc, key, value)
    if isinstance(opts.get("background"), str):  # the command line's names for the usual ones
        named = {"white": [1.0, 1.0, 1.0], "black": [0.0, 0.0, 0.0], "random": None}
        if opts["background"] not in named:
            raise option_error("background", opts["background"], "is not white, black, random or three numbers",
                               "e.g. --background white, or background: [0.5, 0.5, 0.5]", sources.get("background"))
        if opts["background"] == "random":
            opts["random_background"] = True
        opts["background"] = named[opts["background"]]
    for key, value in opts.items():
        target = (cfg if key in _FIT_FIELDS else cfg.train.mcmc if key in MCMC_FIELDS
                  else cfg.train.adc if key in ADC_FLAT else cfg.train)
        setattr(target, key, value)
    if cfg.train.strategy == "adc" and base is None:
        # 3DGS trains without DBS / 3DGS-MCMC's opacity and scale regularisers, and starts as
        # 3DGS does: opacity 0.1, scales at the full neighbour spacing, 100k random points where
        # there are no SfM points (decision 0015: with DBS's start ADC overfits lego by 5 dB)
        for key, value in ADC_START.items():
            if key not in given:
                setattr(cfg.train, key, value)
    cfg.train.backend, cfg.train.device = cfg.backend, cfg.device
    if budget_bytes is not None:
        try:
            total = parse_bytes(budget_bytes)
        except ValueError as e:
            raise option_error("budget_bytes", budget_bytes, str(e).split(" (")[0], "examples: 4194304, 4MB, 512KB",
                                sources.get("budget_bytes")) from None
        check_fit_config(cfg, sources)  # the model below is built from these settings
        per_prim, nets = bytes_per_primitive(cfg)
        if total - nets < per_prim:
            raise option_error("budget_bytes", budget_bytes, f"holds no primitive ({per_prim} bytes each, "
                                f"{nets} for the kernel's networks)", f"give at least {nets + per_prim} bytes",
                                sources.get("budget_bytes"))
        cfg.train.budget = (total - nets) // per_prim
        notes["budget"] = {"budget_bytes": total, "bytes_per_primitive": per_prim, "network_bytes": nets,
                           "budget": cfg.train.budget,
                           "rule": "budget = (budget_bytes - network_bytes) // bytes_per_primitive"}
    elif budget is not None:
        text = str(budget).strip().lower()
        if text.startswith("auto"):
            try:
                cfg.auto_budget = AutoBudgetConfig.from_dict(auto_options or {})
            except (TypeError, ValueError) as e:
                raise option_error("auto_budget", auto_options, str(e), "see AutoBudgetConfig in "
                                   "splatk.stages.autobudget for the settings", sources.get("auto_budget")) from None
            ref = text[4:].lstrip(":")
            if ref:
                cfg.train.budget = _read_count("budget", budget, ref, sources)
            notes["budget"] = {"auto": True, "reference_budget": cfg.train.budget}
        else:
            cfg.train.budget = _read_count("budget", budget, budget, sources)
    if cfg.train.strategy == "adc" and cfg.train.adc.cap_max is None:
        # 3DGS has no cap. A budget the user gives caps clones and splits, so that an
        # equal-memory comparison (paper Tab. 2) holds ADC to it too; without one, the cap only
        # keeps the run inside this machine's memory
        given_budget = budget_bytes is not None or (budget is not None and cfg.auto_budget is None)
        cfg.train.adc.cap_max = cfg.train.budget if given_budget else max_budget(cfg)
    check_fit_config(cfg, sources)
    if base is None:
        fraction = run_fraction(cfg)
        scaled = scale_to_run_length(cfg, keep=given)
        if scaled:
            notes["scaled_schedules"] = {"factor": fraction, **scaled}
    return cfg, notes


def _check_flags_apply(opts: dict, sources: dict, kernel: str, planar: bool, color: str, eval_split: str) -> None:
    """A flag typed on the command line that the chosen kernel or colour model has no use for is an
    error, not silently dropped: `--kernel beta --k 4` would otherwise train Beta and say nothing.
    Presets and bench files may set options for kernels they do not pick, so only the command
    line's own flags are checked."""
    learned = kernel == "learned"
    rules = (("k", learned and not planar, "is an option of the volumetric learned kernel",
              "use --primitive volumetric" if learned else "add --kernel learned"),
             ("kernel_weights", learned, "is an option of the learned kernel", "add --kernel learned"),
             ("sh_degree", color == "sh", "is an option of the SH colour model", "add --color sh"),
             ("test_every", eval_split == "held-out",
              f"chooses held-out test views, and --eval-split {eval_split} holds none out",
              "use --eval-split held-out"))
    for name, applies, problem, fix in rules:
        if name in opts and not applies and sources.get(name) == "command line":
            value = str(opts[name])
            value = int(value) if value.isdigit() else value
            raise option_error(name, value, problem, f"{fix}, or leave the flag out", "command line")


def _weights_path(w) -> str:
    """``default``, ``none``, or the absolute path of a weights file (a resumed run or a bench
    started elsewhere finds it)."""
    if w is None or str(w).lower() in ("none", "default"):
        return "none" if w is None else str(w).lower()
    return str(Path(str(w)).expanduser().absolute())


def _adopt_network_shape(kernel_options: dict) -> None:
    """A weights file from `splatk pretrain` fixes the networks' shape: take the shape options
    it was made with, unless they were given (a mismatch is then the kernel's error)."""
    from ..kernels.learned import ARCH_OPTIONS, WEIGHTS_FORMAT
    from ..kernels.base import read_weights_file

    weights = kernel_options.get("weights")
    if not isinstance(weights, str) or weights.lower() in ("default", "none") or not Path(weights).is_file():
        return
    shape = read_weights_file(Path(weights), WEIGHTS_FORMAT, "learned-kernel", "splatk pretrain").get("options", {})
    for name in ARCH_OPTIONS:
        if name in shape and name not in kernel_options:
            kernel_options[name] = shape[name]


def _read_count(name: str, given, text, sources: dict) -> int:
    if isinstance(text, bool):
        text = "?"
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise option_error(name, given, "not a number of primitives", "give a whole number, or auto / auto:N",
                            sources.get(name)) from None
    if not math.isfinite(value) or value != int(value):
        raise option_error(name, given, "not a whole number", "give a whole number of primitives",
                            sources.get(name))
    return int(value)


def _read_k(value, sources: dict):
    """``--k``: a whole number, or ``auto`` (resolved when the scene is loaded)."""
    text = value.strip().lower() if isinstance(value, str) else None
    if text is None or text == AUTO_K:
        return AUTO_K if text == AUTO_K else value
    if not text.isdigit():
        raise option_error("k", value, "is not a whole number or auto", "e.g. --k 2, --k 8 or --k auto",
                           sources.get("k"))
    return int(text)


# ---- the schema ----------------------------------------------------------------------------------
#: the largest thread count accepted: OpenMP starts this many threads per parallel region
MAX_THREADS = 1024


#: (setting path, flag name, rule). Kernel and colour options are checked by building them.
RULES = [
    ("color", "color", choice("sh", "sb")),
    ("sh_degree", "sh_degree", int_range(0, 3)),
    ("sb_lobes", "sb_lobes", int_range(1, 64)),
    ("primitive", "primitive", choice(*PRIMITIVES)),
    ("downscale", "downscale", float_range(1.0, 1e4)),
    ("test_every", "test_every", int_range(1)),
    ("eval_split", "eval_split", choice(*EVAL_SPLITS)),
    ("train.random_background", "random_background", BOOL),
    ("view_stride", "view_stride", int_range(1)),
    ("threads", "threads", int_range(0, MAX_THREADS)),
    ("nproc", "nproc", int_range(1, 256)),
    ("checkpoint_every", "checkpoint_every", int_range(1)),
    ("train.iters", "iters", int_range(1, 10**9)),
    ("train.time_budget", "time_budget", float_range(0.0, None, lo_open=True)),
    ("train.budget", "budget", int_range(1)),
    ("train.init", "init", choice("auto", "sfm", "random")),
    ("train.random_points", "random_points", int_range(1)),
    ("train.init_scale", "init_scale", float_range(0.0)),
    ("train.random_extent", "random_extent", float_range(0.0, None, lo_open=True)),
    ("train.init_opacity", "init_opacity", float_range(0.0, 0.99, lo_open=True)),
    ("train.seed", "seed", int_range(0, 2**63 - 1)),
    ("train.lambda_dssim", "lambda_dssim", float_range(0.0, 1.0)),
    ("train.opacity_reg", "opacity_reg", float_range(0.0)),
    ("train.scale_reg", "scale_reg", float_range(0.0)),
    ("train.means_lr", "means_lr", float_range(0.0, None, lo_open=True)),
    ("train.means_lr_final", "means_lr_final", float_range(0.0, None, lo_open=True)),
    ("train.sh_degree_interval", "sh_degree_interval", int_range(1)),
    ("train.mcmc.refine_every", "refine_every", int_range(1)),
    ("train.mcmc.refine_start", "refine_start", int_range(0)),
    ("train.mcmc.refine_stop", "refine_stop", float_range(0.0, 1.0)),
    ("train.mcmc.noise_lr", "noise_lr", float_range(0.0)),
    ("train.mcmc.split_scales", "split_scales", choice("keep", "shrink")),
    ("train.mcmc.hold_growth", "hold_growth", BOOL),
    ("train.mcmc.min_opacity", "min_opacity", float_range(0.0, 1.0, lo_open=True)),
    ("train.mcmc.growth", "growth", float_range(1.0)),
    ("train.mcmc.relocate_one_view", "relocate_one_view", BOOL),
    ("scale_schedules", "scale_schedules", BOOL),
    ("short_run_lrs", "short_run_lrs", BOOL),
    ("train.lr_scale", "lr_scale", float_range(0.0, None, lo_open=True)),
    ("train.scales_lr_mult", "scales_lr_mult", float_range(0.0, None, lo_open=True)),
    ("train.snapshot_every", "snapshot_every", int_range(1)),
    ("train.divergence_factor", "divergence_factor", float_range(0.0)),
    ("train.normal_weight", "normal_weight", float_range(0.0)),
    ("train.normal_from", "normal_from", int_range(0)),
    ("train.distortion_weight", "distortion_weight", float_range(0.0)),
    ("train.distortion_from", "distortion_from", int_range(0)),
    ("train.strategy", "strategy", choice(*sorted(STRATEGIES))),
    ("train.batch_views", "batch_views", int_range(1, 256)),
    ("train.adc.densify_from", "densify_from", int_range(0)),
    ("train.adc.densify_until", "densify_until", int_range(0)),
    ("train.adc.densify_every", "densify_every", int_range(1)),
    ("train.adc.opacity_reset_every", "opacity_reset_every", int_range(1)),
    ("train.adc.grad_threshold", "grad_threshold", float_range(0.0, None, lo_open=True)),
    ("train.adc.percent_dense", "percent_dense", float_range(0.0, 1.0, lo_open=True)),
    ("train.adc.min_opacity", "adc.min_opacity", float_range(0.0, 1.0, lo_open=True)),
    ("train.adc.max_screen_size", "adc.max_screen_size", float_range(0.0, None, lo_open=True)),
    ("train.adc.max_world_size", "adc.max_world_size", float_range(0.0, None, lo_open=True)),
    ("train.adc.split_copies", "adc.split_copies", int_range(2, 16)),
    ("train.adc.white_background_reset", "adc.white_background_reset", BOOL),
]


def _get(cfg: FitConfig, path: str):
    obj = cfg
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def check_fit_config(cfg: FitConfig, sources: dict | str | None = None) -> None:
    """InputError naming the first setting of ``cfg`` that is of the wrong type or out of range,
    where it came from (``sources``: flag name -> "command line", "preset ...", ...; a string
    names one source for all) and what is allowed. Checks kernel and colour options by building them, and caps the budget at what
    this machine's memory holds."""
    from ..backends import backend_names
    from ..colors import make_color_model
    from ..kernels import kernel_names, make_kernel

    if isinstance(sources, str):
        sources = {name: sources for _, name, _ in RULES} | {
            n: sources for n in ("backend", "device", "background", "kernel", "kernel_options", "kernel_weights",
                                 "budget", "random_points", "auto_budget")}
    sources = sources or {}
    for path, name, rule in RULES:
        value = _get(cfg, path)
        if value is None and path in ("train.time_budget", "train.random_points"):
            continue
        check_value(name, value, rule, sources)
    backends = ["auto", *backend_names()]
    if cfg.backend not in backends:
        raise option_error("backend", cfg.backend, f"must be one of {', '.join(backends)}",
                            f"use --backend {' or '.join(backends)}", sources.get("backend"))
    if not isinstance(cfg.device, str):
        raise option_error("device", cfg.device, "must be a device name", "use cpu, cuda, cuda:N or mps",
                            sources.get("device"))
    if cfg.background is not None and not (
            isinstance(cfg.background, (list, tuple)) and len(cfg.background) == 3
            and all(valid(c, float_range(0.0, 1.0)) for c in cfg.background)):
        raise option_error("background", cfg.background, "must be three numbers from 0 to 1",
                            "e.g. background: [1, 1, 1]", sources.get("background"))
    kernels = kernel_names(cfg.primitive)
    if not isinstance(cfg.kernel, str):
        raise option_error("kernel", cfg.kernel, "must be a kernel name",
                           f"use one of {', '.join(kernel_names('volumetric'))}", sources.get("kernel"))
    if cfg.kernel not in kernels and cfg.kernel in kernel_names("volumetric"):
        raise InputError(None, f"kernel {cfg.kernel!r} has no {cfg.primitive} version",
                         f"use --kernel {' or '.join(kernels)}, or --primitive volumetric")
    if cfg.kernel not in kernels:
        raise option_error("kernel", cfg.kernel, f"is not a {cfg.primitive} kernel",
                           f"use one of {', '.join(kernels)}", sources.get("kernel"))
    if not isinstance(cfg.kernel_options, dict):
        raise option_error("kernel_options", cfg.kernel_options, "must be a mapping", "e.g. kernel_options: {k: 4}",
                            sources.get("kernel_options"))
    options = dict(cfg.kernel_options)
    if "weights" in options:
        options["weights"] = "none"  # the file is read (and checked) when the model is built
    if options.get("k") == AUTO_K:
        options["k"] = 2  # any k builds the same networks; the scene decides (resolve_auto_k)
    try:
        make_kernel(cfg.kernel, cfg.primitive, **options)
        make_color_model(cfg.color, **color_options(cfg))
    except (ValueError, TypeError) as e:
        raise InputError(None, f"kernel {cfg.kernel!r} options {cfg.kernel_options}: {e}",
                         "see `splatk fit --help` for the learned kernel's options") from None
    weights = cfg.kernel_options.get("weights")
    if weights is not None and not isinstance(weights, str):
        raise option_error("kernel_weights", weights, "must be a file path", "give the path of `splatk pretrain`'s output",
                            sources.get("kernel_weights"))
    cap = max_budget(cfg)
    for path, name in (("train.budget", "budget"), ("train.random_points", "random_points")):
        value = _get(cfg, path)
        if value is not None and value > cap:
            raise option_error(name, value, f"needs about {value * train_bytes_per_primitive(cfg) / 2**30:.1f} GiB to train, "
                                f"more than half of this machine's {memory_bytes() / 2**30:.0f} GiB",
                                f"at most {cap:,} primitives fit here", sources.get(name))
    for name in ("normal_weight", "distortion_weight"):
        if cfg.primitive != "planar" and getattr(cfg.train, name) > 0:
            raise option_error(name, getattr(cfg.train, name), "is a term of planar primitives (2DGS's surfels)",
                               "add --primitive planar, or leave it at 0", sources.get(name))
    if cfg.train.strategy == "adc":
        if cfg.primitive != "volumetric":
            raise InputError(None, "--strategy adc (3DGS's density control) is for volumetric primitives",
                             "use --strategy mcmc with --primitive planar")
        if cfg.auto_budget is not None:
            raise InputError(None, "--budget auto chooses an MCMC budget; ADC grows without one",
                             "use --strategy mcmc with --budget auto, or a number with --strategy adc")
        cap = cfg.train.adc.cap_max
        if cap is not None and not valid(cap, int_range(1, max_budget(cfg))):
            raise option_error("adc.cap_max", cap, f"must be a whole number from 1 to {max_budget(cfg):,} (memory)",
                               "give a smaller cap", sources.get("adc"))
    if cfg.nproc > 1:
        check_processes(cfg, sources)
    if cfg.auto_budget is not None:
        ab = cfg.auto_budget
        if not valid(ab.holdout_every, int_range(2)):
            raise option_error("auto_budget.holdout_every", ab.holdout_every, "must be a whole number of at least 2",
                                "give at least 2", sources.get("auto_budget"))
        if cfg.train.budget * ab.max_factor > cap:
            raise option_error("budget", f"auto:{cfg.train.budget}", f"may try {ab.max_factor:g}x the reference "
                                f"budget, more than this machine's memory holds", f"use auto:N with N at most "
                                f"{int(cap / ab.max_factor):,}", sources.get("budget"))
