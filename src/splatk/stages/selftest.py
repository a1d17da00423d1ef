"""`splatk selftest`: every backend against the torch reference on a fixed small scene.

Each case renders the same inputs through the backend under test (on CUDA where it runs there,
else on the CPU) and through the ``torch`` backend on the CPU, pushes the same random upstream
gradients through both, and compares the images and every input's gradient. Cases: the
volumetric rasteriser for every profile kind, the planar rasteriser (both planar profiles)
and the image splats' renderer (gaussian, gabor and learned kernels). A backend passes when every case is within :data:`TOLERANCES`.
"""
from __future__ import annotations

import math
from typing import Callable

import torch

from .. import backends
from ..backends import Backend, PlanarProfile, Profile
from ..errors import BackendUnavailable

#: float32 backend vs float32 torch reference, per case family: ``image`` is the largest absolute
#: difference of the rendered values (colours and alphas, in [0, 1]); ``grad`` is, per input, the
#: largest absolute gradient difference over the largest reference gradient, maxed over inputs.
#: Each is about 10x the worst seen over the parity tests' inputs (the tests named).
TOLERANCES = {
    # tests/backends/test_cpu_backend.py (cpu: 1.4e-6 / 2.0e-6) and test_triton_backend.py
    # (cuda under Triton's interpreter: 1.4e-6 / 2.5e-6, student_t's nu)
    "raster": {"image": 1e-5, "grad": 3e-5},
    # tests/backends/test_planar_cpu.py's float32 image tolerance (cpu here: 1.2e-7 / 1.2e-6,
    # cuda under the interpreter: 1.2e-7 / 1.4e-6); the gradients go through 2DGS Eq. 10's cross
    # products and divisions, whose rounding a reordered build amplifies near grazing disks:
    # wider headroom
    "planar": {"image": 2e-5, "grad": 1e-4},
    # tests/backends/test_image_cpu.py's float32 image tolerance; its gradients allow 2e-3: the
    # learned kernel's decoder bias sums the table gradients of every pixel (worst seen there:
    # cpu 8e-6, cuda under the interpreter 4e-5)
    "image": {"image": 2e-5, "grad": 2e-4},
}

RASTER_PROFILES = {"gaussian": ("gaussian", 0), "beta": ("beta", 0), "student_t": ("student_t", 0),
                   "table4": ("table", 4), "table20": ("table", 20)}
WIDTH, HEIGHT = 32, 24


def _rand(gen: torch.Generator, *shape, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
    return torch.rand(*shape, generator=gen) * (hi - lo) + lo


def raster_inputs(kind: str, k: int, seed: int = 0) -> tuple[dict, dict]:
    """(differentiable inputs, fixed inputs) of the 2D splat case: 24 splats on 32 x 24 pixels,
    some reaching past the border, one nearly opaque pile in the middle (early termination)."""
    gen = torch.Generator().manual_seed(seed)
    n = 24
    means = torch.stack([_rand(gen, n, lo=-3, hi=WIDTH + 3), _rand(gen, n, lo=-3, hi=HEIGHT + 3)], -1)
    means[:6] = torch.tensor([WIDTH / 2, HEIGHT / 2]) + _rand(gen, 6, 2, lo=-2, hi=2)
    sig = _rand(gen, n, 2, lo=0.8, hi=5.0)
    theta = _rand(gen, n, hi=math.pi)
    c, s = torch.cos(theta), torch.sin(theta)
    i0, i1 = 1 / sig[:, 0] ** 2, 1 / sig[:, 1] ** 2
    conics = torch.stack([c * c * i0 + s * s * i1, c * s * (i0 - i1), s * s * i0 + c * c * i1], -1) / 9.0
    opac = _rand(gen, n, lo=0.2, hi=1.0)
    opac[:6] = 0.98
    leaves = {"means2d": means, "conics": conics, "opacities": opac, "colors": _rand(gen, n, 3),
              "background": _rand(gen, 3)}
    if kind == "beta":
        leaves["params"] = _rand(gen, n, 1, lo=0.3, hi=4.0)
    elif kind == "student_t":
        leaves["params"] = _rand(gen, n, 1, lo=0.5, hi=10.0)
    elif kind == "table":
        leaves["params"] = _rand(gen, n, k, hi=1.2)  # samples above 1 reach the 0.999 clamp
    return leaves, {"depths": _rand(gen, n, lo=1.0, hi=5.0), "kind": kind}


def render_raster(backend: Backend, x: dict, fixed: dict) -> tuple[torch.Tensor, ...]:
    profile = Profile(fixed["kind"], x.get("params"))
    out = backend.rasterize(x["means2d"], x["conics"], x["opacities"], x["colors"], fixed["depths"],
                            profile, WIDTH, HEIGHT, x["background"])
    return out.colors, out.alphas


def planar_inputs(kind: str, seed: int = 0) -> tuple[dict, dict]:
    """16 disks in front of an identity camera (f = 30 px), random orientations and sizes."""
    gen = torch.Generator().manual_seed(seed)
    n = 16
    means = torch.stack([_rand(gen, n, lo=-1.2, hi=1.2), _rand(gen, n, lo=-0.9, hi=0.9),
                         _rand(gen, n, lo=2.5, hi=4.5)], 1)
    quats = torch.randn(n, 4, generator=gen)
    leaves = {"means": means, "quats": quats / quats.norm(dim=1, keepdim=True),
              "scales": _rand(gen, n, 2, lo=0.05, hi=0.3), "opacities": _rand(gen, n, lo=0.2, hi=0.95),
              "colors": _rand(gen, n, 3), "background": _rand(gen, 3)}
    if kind == "grid":
        leaves["table"] = _rand(gen, n, 6, 6, lo=0.2, hi=1.0)
    fixed = {"viewmat": torch.eye(4), "kind": kind,
             "K": torch.tensor([[30.0, 0, WIDTH / 2], [0, 30.0, HEIGHT / 2], [0, 0, 1]])}
    return leaves, fixed


def render_planar(backend: Backend, x: dict, fixed: dict) -> tuple[torch.Tensor, ...]:
    out = backend.rasterize_planar(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                   fixed["viewmat"], fixed["K"], WIDTH, HEIGHT,
                                   PlanarProfile(fixed["kind"], x.get("table")), x["background"])
    return out.colors, out.alphas


def _splats_2d():
    from ..image.model import Splats2D

    return Splats2D


def image_inputs(kernel: str, seed: int = 0) -> tuple[dict, dict]:
    """24 image splats of ``kernel`` on 32 x 24 pixels, some sheared and some past the border,
    every kernel parameter away from its init; the model's own parameters are the inputs."""
    gen = torch.Generator().manual_seed(seed)
    with torch.random.fork_rng(devices=[]):  # the decoder's layers draw from the global generator
        torch.manual_seed(seed)
        model = _splats_2d()(kernel, 24, HEIGHT, WIDTH, generator=gen)
    with torch.no_grad():
        model.xy_raw.mul_(1.6)
        model.colors.normal_(0.0, 1.0, generator=gen)
        model.chol.mul_(_rand(gen, *model.chol.shape, lo=0.3, hi=2.3))
        if kernel == "gabor":
            model.gabor_amps.normal_(0.0, 1.0, generator=gen)
            model.gabor_freqs.uniform_(0.0, 3.0, generator=gen)
        if kernel == "learned":  # the decoder starts as the constant 1, which passes no gradient
            model.latents.normal_(0.0, 1.0, generator=gen)
            for p in model.decoder.parameters():
                p.add_(0.5 * torch.randn(p.shape, generator=gen))
    return {}, {"model": model}


def render_image(backend: Backend, x: dict, fixed: dict) -> tuple[torch.Tensor, ...]:
    return (fixed["model"].render(backend=backend),)


#: the backend op each case family exercises
FAMILY_OPS = {"raster": "rasterize", "planar": "rasterize_planar", "image": "render_image_splats"}


def cases() -> dict[str, tuple[str, Callable, Callable]]:
    """name -> (tolerance family, inputs(), render(backend, leaves, fixed))."""
    table = {}
    for name, (kind, k) in RASTER_PROFILES.items():
        table[f"raster_{name}"] = ("raster", lambda kind=kind, k=k: raster_inputs(kind, k), render_raster)
    for kind in ("gaussian_surfel", "grid"):
        table[f"planar_{kind}"] = ("planar", lambda kind=kind: planar_inputs(kind), render_planar)
    for kernel in ("gaussian", "gabor", "learned"):
        table[f"image_{kernel}"] = ("image", lambda kernel=kernel: image_inputs(kernel), render_image)
    return table


def has_own_op(backend: Backend, reference: Backend, family: str) -> bool:
    """Whether ``backend`` has its own version of the family's op (else it runs the torch one)."""
    op = FAMILY_OPS[family]
    return getattr(type(backend), op, None) not in (None, getattr(type(reference), op, None))


def _run(backend: Backend, make_inputs: Callable, render: Callable) -> tuple[list, dict]:
    """Outputs and input gradients (on the CPU) of one render with fixed upstream gradients."""
    leaves, fixed = make_inputs()
    device = backend.device
    fixed = {k: v.to(device) if hasattr(v, "to") else v for k, v in fixed.items()}
    if "model" in fixed:
        x = dict(fixed["model"].named_parameters())
    else:
        x = {k: v.to(device).requires_grad_(True) for k, v in leaves.items()}
    outs = render(backend, x, fixed)
    gen = torch.Generator().manual_seed(7)
    loss = sum((o * torch.randn(o.shape, generator=gen).to(device)).sum() for o in outs)
    loss.backward()
    grads = {k: torch.zeros_like(v) if v.grad is None else v.grad for k, v in x.items()}
    return [o.detach().cpu() for o in outs], {k: g.detach().cpu() for k, g in grads.items()}


def compare(got: tuple[list, dict], ref: tuple[list, dict]) -> tuple[float, float]:
    """(max absolute output difference, max over inputs of the gradient difference relative to
    the largest reference gradient); a NaN difference counts as infinite."""

    def worst(diff: torch.Tensor) -> float:
        value = float(diff.abs().max()) if diff.numel() else 0.0
        return math.inf if math.isnan(value) else value

    image_error = max(worst(g - r) for g, r in zip(got[0], ref[0]))
    grad_error = 0.0
    for name, r in ref[1].items():
        scale = max(float(r.abs().max()), 1e-6) if r.numel() else 1.0
        grad_error = max(grad_error, worst(got[1][name] - r) / scale)
    return image_error, grad_error


def backend_device(name: str) -> torch.device | None:
    """Where ``name`` is tested: CUDA when it runs there, else the CPU; None where neither."""
    candidates = ([torch.device("cuda")] if torch.cuda.is_available() else []) + [torch.device("cpu")]
    for device in candidates:
        if backends.is_available(name, device):
            return device
    return None


def check_backend(name: str, only: list[str] | None = None) -> dict:
    """One backend's report: passed, device, max errors and each case's errors."""
    device = backend_device(name)
    if device is None:
        raise BackendUnavailable(_reason(name))
    backend, reference = backends.get(name, device), backends.get("torch", "cpu")
    report = {"device": str(device), "cases": {}}
    for case, (family, make_inputs, render) in cases().items():
        if only is not None and case not in only:
            continue
        tol = TOLERANCES[family]
        try:
            image_error, grad_error = compare(_run(backend, make_inputs, render),
                                              _run(reference, make_inputs, render))
        except Exception as e:  # a backend that raises fails the case, and the others still run
            report["cases"][case] = {"passed": False, "error": f"{type(e).__name__}: {e}"}
            continue
        ok = image_error <= tol["image"] and grad_error <= tol["grad"]
        report["cases"][case] = {"passed": bool(ok), "image_error": image_error, "grad_error": grad_error,
                                 "image_tolerance": tol["image"], "grad_tolerance": tol["grad"],
                                 "own_op": has_own_op(backend, reference, family)}
    done = [c for c in report["cases"].values() if "image_error" in c]
    report["passed"] = all(c["passed"] for c in report["cases"].values())
    report["max_image_error"] = max((c["image_error"] for c in done), default=0.0)
    report["max_grad_error"] = max((c["grad_error"] for c in done), default=0.0)
    return report


def run_selftest(backend: str = "all", only: list[str] | None = None) -> dict:
    """``{"backends": {name: report}, "skipped": {name: reason}}`` for ``backend`` (a name or
    ``all``: every registered backend that runs here; the others are listed as skipped).

    Raises:
        ValueError: an unknown backend name.
        splatk.errors.BackendUnavailable: the named backend runs on no device here.
    """
    names = backends.backend_names()
    if backend != "all" and backend not in names:
        raise ValueError(f"unknown backend {backend!r}; choose from {', '.join(names)}, all")
    result = {"backends": {}, "skipped": {}}
    for name in names if backend == "all" else [backend]:
        if backend == "all" and backend_device(name) is None:
            result["skipped"][name] = _reason(name)
            continue
        result["backends"][name] = check_backend(name, only)
    result["passed"] = all(r["passed"] for r in result["backends"].values())
    return result


def _reason(name: str) -> str:
    try:
        backends.get(name, "cpu")
    except BackendUnavailable as e:
        return str(e)
    return "unavailable"
