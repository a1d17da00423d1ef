"""The learned, view-dependent splatting kernel (paper Sec. 4.1-4.3).

Each primitive carries a 3D-kernel latent ``z3d`` [N, latent_dim] (zero at init, paper Sec. 4.5).
For one view, the global projection MLP maps the latent and the primitive's camera-space
attributes to a 2D-kernel latent (paper Eq. 5)::

    z2d = Phi_proj(z3d, mu_cam, s, R_cam)          # 4 linear layers, 64 wide, leaky ReLU

and the global decoder turns it into a radially symmetric profile of the squared normalised
radius (paper Eq. 6)::

    d = Phi_dec(r^2, z2d)                          # 3 linear layers, 4 wide, leaky ReLU, sigmoid

The rasteriser never calls Phi_dec per pixel: :meth:`LearnedKernel.profile` samples it at
``k`` radii ``r_i = i / (k - 1)`` (paper Eq. 7) for all visible primitives in one batched call,
and the backends interpolate linearly in ``r`` (``Profile("table", d[M, k])``, paper Eq. 8).
The support is the 1-sigma bounding ellipse (DBS convention), so ``r = 1`` is its edge; the
sample there is bounded by ``edge_max`` (see the class docstring) so the kernel falls to its edge.

Input encoding of Phi_proj (the paper leaves it open). Scene units are arbitrary (COLMAP
scenes span 1 to 1000 units), so raw ``mu_cam`` and ``s`` would put the network off the
range it was pretrained on. We feed, per primitive (``rho = |mu_cam|``):

* ``z``:  ``z3d`` as is                                    (latent_dim values)
* ``mu``: ``mu_cam / rho`` (viewing direction, unit-free) and ``log(rho) / 2.5``   (4 values)
* ``s``:  ``(log(s / rho) + 5) / 2.5``: the angular size of each axis, which is what the
  projection sees and is invariant to the scene's unit; -1.7 to 1.1 for splats of 0.1 to
  100 px at a 1000 px focal length                                                  (3 values)
* ``R``:  ``R_cam`` flattened row-major                                             (9 values)

Only ``log(rho)`` depends on the unit; pretraining samples it over [-3, 5] (0.05 to 150
units) and the angular size over [e^-12, 1], and the target depends on neither, so the
pretrained network (nearly) ignores them until scene training gives it a reason not to.
Gradients flow through these inputs into the geometry (means, scales, quats) as well.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..backends import Profile
from .base import Kernel, ViewContext, read_weights_file, register_kernel, scale_learned_options

#: the shipped pretrained networks (cosine target, default architecture), made by
#: ``splatk pretrain --target cosine --out src/splatk/assets/learned_cosine.pt``
DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "assets" / "learned_cosine.pt"
WEIGHTS_FORMAT = "splatk-learned-kernel"

#: the four input groups of Phi_proj (paper Eq. 5, Tab. 3 ablation)
PROJ_INPUTS = ("z", "mu", "s", "R")
#: width of each input group after encoding (z: latent_dim)
_ENC_WIDTH = {"mu": 4, "s": 3, "R": 9}
LEAKY_SLOPE = 0.01
#: encoding constants (see the module docstring)
LOG_DIST_SCALE = 2.5
LOG_ANGLE_SHIFT = 5.0
LOG_ANGLE_SCALE = 2.5
#: the decoded profile's value at the support edge (r = 1) is at most this (see ``edge_max``)
EDGE_MAX = 0.25
#: the scale regulariser's weight on this kernel's scales: its 1-sigma support over the
#: Gaussian's 3 (see ``scale_reg_weight``)
SCALE_REG_WEIGHT = 1.0 / 3.0
#: the power of the interior samples' envelope (see ``envelope_power``)
ENVELOPE_POWER = 4.0
#: options that fix the networks' shapes; a weights file must match them
ARCH_OPTIONS = ("latent_dim", "latent2d_dim", "proj_width", "dec_width", "proj_inputs")


def _use_bf16(precision: str, grad_enabled: bool) -> bool:
    if precision == "bf16":
        return True
    if precision == "fp32" or grad_enabled:
        return False
    return _cpu_has_bf16()  # "auto", no gradients


@functools.lru_cache(maxsize=1)
def _cpu_has_bf16() -> bool:
    """Whether the CPU multiplies bf16 natively (AVX-512 BF16, AMX); asked once."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def parse_proj_inputs(spec) -> tuple[str, ...]:
    """"z,mu,s,R" (any order, any subset; list or comma string) -> canonical ordered tuple."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names = []
    for item in items:
        item = item.strip()
        name = "R" if item in ("R", "r", "rot", "R_cam") else item
        if name not in PROJ_INPUTS:
            raise ValueError(f"unknown Phi_proj input {item!r}; choose a subset of z,mu,s,R")
        names.append(name)
    if not names:
        raise ValueError("Phi_proj needs at least one input (a subset of z,mu,s,R)")
    return tuple(n for n in PROJ_INPUTS if n in names)


def _he_init(layer: nn.Linear) -> None:
    """He et al. 2015 init for leaky-ReLU layers (paper Sec. 4.5); zero bias."""
    nn.init.kaiming_normal_(layer.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
    nn.init.zeros_(layer.bias)


def _mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers with leaky ReLU after all but the last."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        lin = nn.Linear(a, b)
        _he_init(lin)
        layers.append(lin)
        if i < len(sizes) - 2:
            layers.append(nn.LeakyReLU(LEAKY_SLOPE))
    return nn.Sequential(*layers)


def phi_dec(w1, b1, w2, b2, w3, b3, z2d, r2, logits: bool = False) -> torch.Tensor:
    """Phi_dec as a function of its weights (paper Eq. 6): see :meth:`LearnedKernel.decode`.

    The first layer is linear in (r^2, z2d): its z2d part is computed once per primitive and
    the r^2 part broadcast over the radii, so no [M, P, 1 + L] input is ever built.
    """
    h = F.linear(z2d, w1[:, 1:], b1)[..., None, :] + r2[..., None] * w1[:, 0]  # [M, P, W]
    h = F.leaky_relu(h, LEAKY_SLOPE)
    h = F.leaky_relu(F.linear(h, w2, b2), LEAKY_SLOPE)
    out = F.linear(h, w3, b3)[..., 0]
    return out if logits else torch.sigmoid(out)


@register_kernel
class LearnedKernel(Kernel):
    """Learned view-dependent kernel: per-primitive ``z3d`` plus global Phi_proj / Phi_dec.

    Args:
        k: profile samples per primitive and view (2, 4 or 8; paper Sec. 4.3, default 2).
        latent_dim: size of ``z3d`` (paper: 5).
        latent2d_dim: size of ``z2d`` (paper: 5).
        proj_width: hidden width of Phi_proj (paper: 64).
        dec_width: hidden width of Phi_dec (paper: 4).
        proj_inputs: which inputs Phi_proj sees, a subset of "z,mu,s,R" (paper Tab. 3).
        freeze_iters: the networks are frozen for this many iterations (paper: 2000).
        net_lr, net_lr_final: the networks' LR decays exponentially between these after the
            freeze (paper: 1.6e-4 -> 1.6e-6).
        net_lr_mult: multiplies the network LR; None = 10 without pretrained weights (paper
            Sec. 5.4, "no pre-train"), else 1.
        proj_lr_mult: multiplies Phi_proj's LR on top of that (Phi_dec keeps the networks' LR);
            1 is the paper's rate.
        envelope_power: p of the envelope that bounds the interior samples (k > 2): each is at
            most d(0) (1 - (1 - edge_max) r^p). Without it, Phi_proj turned some primitives'
            profiles into boxes (flat to r = 5/7, then a cliff to the edge bound); large ones
            then spilled past the surfaces they covered and a k = 8 fit diverged. The
            pretrained cosine lies under the envelope at p = 4, so frozen networks draw what
            they drew; 0 turns the envelope off
            (docs/decisions/0104-learned-kernel-profile-envelope.md).
        z3d_lr: Adam LR of the per-primitive latents (the paper does not give one). After
            pretraining a unit change of z3d moves the logits of d(0) + d(1) by 1-2.5, so 1e-4
            lets a latent travel a few units over a 30k-iteration fit; on `cup` (1/8 size, 1,500
            iterations) 3e-4 to 3e-3 scored lower on the test and the train views alike.
        weights: pretrained networks from `splatk pretrain`: "default" (the shipped cosine
            file), a path, or "none" (He init, for the no-pretraining ablation).
        edge_max: the profile sample at the support edge (r = 1) is Phi_dec's value there times
            this, so the kernel falls to at most ``edge_max`` where the rasteriser cuts it off.
            The rasteriser's gradients with respect to a primitive's geometry (means, scales,
            rotation) come from the profile's slope inside the support; the cut-off edge itself
            is not differentiated. Unbounded, the networks raise d(1) towards d(0) after the
            freeze (more coverage per primitive), which flattens the profile into a box whose
            geometry gets no gradient but the scale regulariser's: the scales shrink, the
            networks widen the profile further, and the loss climbs
            (docs/decisions/0101-learned-kernel-unfreeze.md). 1 leaves Phi_dec's value as is.
        scale_reg_weight: the scale regulariser (``scale_reg`` x mean scale, from DBS / 3DGS-MCMC)
            charges this kernel's scales times this. Its support ends at 1 sigma where the
            Gaussian's ends at 3, so for the same footprint on screen its scales are a third of a
            Gaussian's; the default 1/3 charges the footprint as the Gaussian's regulariser does.
            At 1 the regulariser pulls the learned kernel's footprints three times as hard, and
            on forward-facing scenes the scales shrink until the loss rises
            (docs/decisions/0102-learned-kernel-scale-regulariser-and-auto-k.md).
        proj_precision: arithmetic of Phi_proj's matrix products: "fp32", "bf16" (CPU autocast;
            weights, inputs and z2d stay float32, Phi_dec stays float32), or "auto": bf16 for
            renders without gradients (eval, export) on a CPU with native bf16 units, fp32
            otherwise. Phi_proj is most of the learned kernel's render cost, and bf16 cuts it
            about 3.5x on AVX-512; training stays fp32, where bf16 was slower on this machine.
    """

    name = "learned"
    support_sigmas = 1.0
    needs_view = True

    @classmethod
    def scale_to_run(cls, options: dict, factor: float, keep=frozenset(), schedules: bool = True,
                     lrs: bool = True) -> dict:
        return scale_learned_options(options, factor, keep, schedules, lrs, "z3d_lr", 1e-4, 2000)

    def __init__(
        self,
        k: int = 2,
        latent_dim: int = 5,
        latent2d_dim: int = 5,
        proj_width: int = 64,
        dec_width: int = 4,
        proj_inputs="z,mu,s,R",
        freeze_iters: int = 2000,
        net_lr: float = 1.6e-4,
        net_lr_final: float = 1.6e-6,
        net_lr_mult: float | None = None,
        z3d_lr: float = 1e-4,
        weights: str | None = "default",
        proj_precision: str = "auto",
        proj_lr_mult: float = 1.0,
        envelope_power: float = ENVELOPE_POWER,
        edge_max: float = EDGE_MAX,
        scale_reg_weight: float = SCALE_REG_WEIGHT,
    ):
        super().__init__()
        k = int(k)
        if k < 2:
            raise ValueError(f"learned kernel: k must be >= 2 (paper uses 2, 4, 8), got {k}")
        self.k = k
        self.latent_dim = int(latent_dim)
        self.latent2d_dim = int(latent2d_dim)
        self.proj_width = int(proj_width)
        self.dec_width = int(dec_width)
        self.inputs = parse_proj_inputs(proj_inputs)
        self.freeze_iters = int(freeze_iters)
        self.net_lr = float(net_lr)
        self.net_lr_final = float(net_lr_final)
        self.z3d_lr = float(z3d_lr)
        if proj_precision not in ("auto", "fp32", "bf16"):
            raise ValueError(f"learned kernel: proj_precision must be auto, fp32 or bf16, got {proj_precision!r}")
        self.proj_precision = proj_precision
        self.proj_lr_mult = float(proj_lr_mult)
        if not (self.proj_lr_mult >= 0.0 and math.isfinite(self.proj_lr_mult)):
            raise ValueError(f"learned kernel: proj_lr_mult must be a number >= 0, got {proj_lr_mult}")
        self.edge_max = float(edge_max)
        if not 0.0 < self.edge_max <= 1.0:
            raise ValueError(f"learned kernel: edge_max must be in (0, 1], got {edge_max}")
        self.scale_reg_weight = float(scale_reg_weight)
        if not (self.scale_reg_weight >= 0.0 and math.isfinite(self.scale_reg_weight)):
            raise ValueError(f"learned kernel: scale_reg_weight must be a number >= 0, got {scale_reg_weight}")
        w = "none" if weights is None else str(weights)
        self.weights = w
        pretrained = w.lower() != "none"
        self.net_lr_mult = float(net_lr_mult) if net_lr_mult is not None else (1.0 if pretrained else 10.0)

        in_dim = sum(self.latent_dim if n == "z" else _ENC_WIDTH[n] for n in self.inputs)
        w64 = self.proj_width
        self.proj = _mlp([in_dim, w64, w64, w64, self.latent2d_dim])  # Phi_proj, paper Eq. 5
        self.dec = _mlp([1 + self.latent2d_dim, self.dec_width, self.dec_width, 1])  # Phi_dec, Eq. 6
        radii = torch.linspace(0.0, 1.0, k)
        self.register_buffer("radii2", radii * radii, persistent=False)  # r_i^2, paper Eq. 7
        edge = torch.ones(k)
        edge[-1] = self.edge_max
        self.register_buffer("sample_bound", edge, persistent=False)  # [k]: edge_max at r = 1
        self.envelope_power = float(envelope_power)
        envelope = 1.0 - (1.0 - self.edge_max) * radii ** max(self.envelope_power, 1e-6)
        envelope[-1] = 1e30  # the edge sample has its own bound
        self.register_buffer("envelope", envelope, persistent=False)

        # A missing weights file is reported at first use, not here: load_model() rebuilds the
        # kernel from its options and then loads the saved networks over it, which must work
        # even where the original weights file no longer exists.
        self._missing_weights: Path | None = None
        self.register_load_state_dict_post_hook(self._loaded_state)
        if pretrained:
            path = DEFAULT_WEIGHTS if w == "default" else Path(w).expanduser()
            if path.is_file():
                self.load_pretrained(path)
            else:
                self._missing_weights = path

    # ---- options and weights -----------------------------------------------------------
    @property
    def options(self) -> dict:
        """Every constructor option, resolved (JSON/YAML serialisable)."""
        return {
            "k": self.k,
            "latent_dim": self.latent_dim,
            "latent2d_dim": self.latent2d_dim,
            "proj_width": self.proj_width,
            "dec_width": self.dec_width,
            "proj_inputs": ",".join(self.inputs),
            "freeze_iters": self.freeze_iters,
            "net_lr": self.net_lr,
            "net_lr_final": self.net_lr_final,
            "net_lr_mult": self.net_lr_mult,
            "z3d_lr": self.z3d_lr,
            "weights": self.weights,
            "proj_precision": self.proj_precision,
            "proj_lr_mult": self.proj_lr_mult,
            "envelope_power": self.envelope_power,
            "edge_max": self.edge_max,
            "scale_reg_weight": self.scale_reg_weight,
        }

    def arch_options(self) -> dict:
        return {name: self.options[name] for name in ARCH_OPTIONS}

    @staticmethod
    def _loaded_state(module, incompatible) -> None:
        module._missing_weights = None

    def load_pretrained(self, path: str | Path) -> dict:
        """Load networks written by :func:`splatk.stages.pretrain.run_pretrain`; returns the
        file's metadata (target, error)."""
        from ..errors import InputError

        path = Path(path)
        obj = read_weights_file(path, WEIGHTS_FORMAT, "learned-kernel", "splatk pretrain")
        theirs = {n: obj["options"].get(n) for n in ARCH_OPTIONS}
        theirs["proj_inputs"] = ",".join(parse_proj_inputs(theirs["proj_inputs"]))
        ours = self.arch_options()
        if theirs != ours:
            diff = ", ".join(f"{n}: file {theirs[n]} vs kernel {ours[n]}" for n in ARCH_OPTIONS
                             if theirs[n] != ours[n])
            raise InputError(path, f"weights are for another network shape ({diff})",
                             "pretrain with the same kernel options (`splatk pretrain`) or pass "
                             "weights: none")
        self.load_state_dict(obj["state_dict"])
        return {k: v for k, v in obj.items() if k != "state_dict"}

    def _check_weights(self) -> None:
        if self._missing_weights is not None:
            from ..errors import InputError

            raise InputError(self._missing_weights, "learned-kernel weights file not found",
                             "make it with `splatk pretrain`, pass another --kernel-weights, "
                             "or weights: none for random init")

    # ---- per-primitive parameters and schedules ---------------------------------------
    def init_primitive_params(self, n, device):
        if "z" not in self.inputs:
            return {}
        return {"z3d": torch.zeros(n, self.latent_dim, device=device)}  # paper Sec. 4.5

    def learning_rates(self):
        return {"z3d": self.z3d_lr} if "z" in self.inputs else {}

    def network_groups(self):
        return [(list(self.proj.parameters()), self.proj_lr_mult), (list(self.dec.parameters()), 1.0)]

    def network_learning_rate(self, it: int, progress: float) -> float:
        """0 for the first ``freeze_iters`` iterations (paper Sec. 4.5, stage one), then an
        exponential decay net_lr -> net_lr_final over the remaining progress."""
        if it <= self.freeze_iters or self.net_lr <= 0:
            return 0.0
        # progress at the end of the freeze, from the ratio progress / iteration (exact when
        # progress counts iterations; a good estimate under a time budget)
        p0 = progress * self.freeze_iters / max(it, 1)
        q = 1.0 if p0 >= 1.0 else min(1.0, max(0.0, (progress - p0) / (1.0 - p0)))
        lo = max(self.net_lr_final, 1e-30)
        lr = math.exp((1.0 - q) * math.log(self.net_lr) + q * math.log(lo))
        return lr * self.net_lr_mult

    # ---- the networks -----------------------------------------------------------------
    def encode(self, z3d: torch.Tensor | None, view: ViewContext) -> torch.Tensor:
        """Phi_proj's input [M, D] (see the module docstring), built with one cat."""
        mu = view.means_cam
        if view.backend is not None:  # one native pass where the backend has one (same values)
            native = view.backend.learned_encode(
                z3d if "z" in self.inputs else None, mu, view.scales, view.rotmats_cam,
                "mu" in self.inputs, "s" in self.inputs, "R" in self.inputs,
                LOG_DIST_SCALE, LOG_ANGLE_SHIFT, LOG_ANGLE_SCALE)
            if native is not None:
                return native
        parts = []
        if "z" in self.inputs:
            parts.append(z3d)
        if "mu" in self.inputs or "s" in self.inputs:
            rho = torch.linalg.vector_norm(mu, dim=1, keepdim=True).clamp_min(1e-12)
            log_rho = torch.log(rho)
        if "mu" in self.inputs:
            parts += [mu / rho, log_rho * (1.0 / LOG_DIST_SCALE)]
        if "s" in self.inputs:
            parts.append((torch.log(view.scales) - log_rho + LOG_ANGLE_SHIFT) * (1.0 / LOG_ANGLE_SCALE))
        if "R" in self.inputs:
            parts.append(view.rotmats_cam.reshape(-1, 9))
        return torch.cat(parts, 1) if len(parts) > 1 else parts[0]

    def project(self, z3d: torch.Tensor | None, view: ViewContext) -> torch.Tensor:
        """z2d = Phi_proj(z3d, mu_cam, s, R_cam) (paper Eq. 5): [M, latent2d_dim]."""
        x = self.encode(z3d, view)
        if x.device.type == "cpu" and _use_bf16(self.proj_precision, torch.is_grad_enabled()):
            with torch.autocast("cpu", dtype=torch.bfloat16):
                z2d = self.proj(x)
            return z2d.float()
        return self.proj(x)

    def decode(self, z2d: torch.Tensor, r2: torch.Tensor, logits: bool = False) -> torch.Tensor:
        """d = Phi_dec(r^2, z2d) (paper Eq. 6) at many radii per primitive.

        Args:
            z2d: [M, latent2d_dim].
            r2: [P] radii^2 shared by all primitives, or [M, P] per primitive.
            logits: return the pre-sigmoid values instead (pretraining's loss uses them).

        Returns:
            [M, P] profile values in (0, 1) (or their logits).
        """
        first, _, mid, _, last = self.dec
        return phi_dec(first.weight, first.bias, mid.weight, mid.bias, last.weight, last.bias,
                       z2d, r2, logits)

    def _proj_layers(self) -> list[nn.Linear]:
        return [m for m in self.proj if isinstance(m, nn.Linear)]

    def _fits_native_profile(self) -> bool:
        # learned_profile's stack buffers: Phi_proj layers up to 256 wide, Phi_dec up to 64
        widths = [w for m in self._proj_layers() for w in (m.in_features, m.out_features)]
        return max(widths) <= 256 and self.dec_width <= 64

    def profile(self, prims, view: ViewContext) -> Profile:
        """Samples d_i = Phi_dec(r_i^2, z2d) at r_i = i / (k - 1) (paper Eq. 7): table [M, k]."""
        self._check_weights()
        native = view.backend
        if native is not None and _use_bf16(self.proj_precision, False) and self._fits_native_profile():
            # encode, Phi_proj in bf16 and Phi_dec in one native pass (the values of the path below)
            table = native.learned_profile(
                prims.get("z3d") if "z" in self.inputs else None, view.means_cam, view.scales,
                view.rotmats_cam, "mu" in self.inputs, "s" in self.inputs, "R" in self.inputs,
                LOG_DIST_SCALE, LOG_ANGLE_SHIFT, LOG_ANGLE_SCALE,
                self._proj_layers(), self.dec[0::2], self.radii2, LEAKY_SLOPE)
            if table is not None:
                return Profile("table", self.bound(table))
        z2d = self.project(prims.get("z3d"), view)
        if native is not None:  # one native pass where the backend has one (same values)
            first, _, mid, _, last = self.dec
            table = native.learned_decode(z2d, (first, mid, last), self.radii2, LEAKY_SLOPE)
            if table is not None:
                return Profile("table", self.bound(table))
        return Profile("table", self.samples(z2d))

    def samples(self, z2d: torch.Tensor) -> torch.Tensor:
        """The k profile samples the rasteriser interpolates (paper Eq. 7), bounded (:meth:`bound`): [M, k]."""
        return self.bound(self.decode(z2d, self.radii2))

    def bound(self, table: torch.Tensor) -> torch.Tensor:
        """Phi_dec's samples [M, k] -> the table drawn: the one at the support edge times
        ``edge_max``, and (``envelope_power`` > 0) each interior sample at most d(0) times the
        envelope 1 - (1 - edge_max) r^p."""
        table = table * self.sample_bound
        if self.envelope_power > 0 and self.k > 2:
            table = torch.minimum(table, table[:, :1] * self.envelope)
        return table

    # ---- export to plain Gaussians ----------------------------------------------------
    def gaussian_scale_factor(self, prims, n_views: int = 6, depth_over_scale: float = 100.0,
                              chunk: int = 65536) -> torch.Tensor:
        """Per-primitive f such that a Gaussian of scale ``f * s`` has the second moment of the
        view-averaged kernel (:func:`splatk.kernels.learned_export.gaussian_scale_factor`)."""
        from .learned_export import gaussian_scale_factor

        self._check_weights()
        return gaussian_scale_factor(self, prims, n_views, depth_over_scale, chunk)
