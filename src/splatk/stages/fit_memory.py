"""What the model a fit builds takes in memory: bytes per primitive as stored, and the most
primitives this machine can train. ``cfg`` is a :class:`splatk.stages.fit_config.FitConfig`
(not imported: that module checks budgets with these functions)."""
from __future__ import annotations

import torch

from ..kernels.auto_k import AUTO_K
from ..machine import memory_bytes

#: training memory per float of a primitive's parameters, an upper estimate: the parameter, its
#: gradient and Adam's two moments take 16 bytes; the rest covers the projected copies, the
#: rollback snapshot, the checkpoint being written and the rasteriser's per-pixel lists
TRAIN_BYTES_PER_FLOAT = 50
#: a fit may plan on at most this share of the machine's memory
MEMORY_SHARE = 0.5


def color_options(cfg) -> dict:
    return {"sh_degree": cfg.sh_degree} if cfg.color == "sh" else {"num_lobes": cfg.sb_lobes}


def bytes_per_primitive(cfg) -> tuple[int, int]:
    """(bytes per primitive, bytes of the global networks) of the model `fit` builds with ``cfg``,
    counted from the model itself: 4 x ``floats_per_primitive()`` and 4 x network parameters."""
    from ..models.planar import PlanarModel
    from ..models.volumetric import SplatModel

    model_class = PlanarModel if cfg.primitive == "planar" else SplatModel
    options = dict(cfg.kernel_options)
    if options.get("k") == AUTO_K:
        options["k"] = 2  # k does not change the bytes (the samples are decoded per view)
    model = model_class.from_points(torch.zeros(1, 3), torch.zeros(1, 3), kernel=cfg.kernel, color=cfg.color,
                                    kernel_options=options, color_options=color_options(cfg))
    return 4 * model.floats_per_primitive(), 4 * sum(p.numel() for p in model.kernel.parameters())


def train_bytes_per_primitive(cfg) -> int:
    """Upper estimate of the memory one primitive takes while training with ``cfg``."""
    floats = 59 if cfg.color == "sh" else 30  # SH degree 3: 48 colour floats; Beta lobes fewer
    floats += 8  # latents, per-primitive kernel parameters
    return TRAIN_BYTES_PER_FLOAT * floats


def max_budget(cfg) -> int:
    """The most primitives a fit with ``cfg`` can hold in this machine's memory share."""
    return max(1, int(MEMORY_SHARE * memory_bytes() / train_bytes_per_primitive(cfg)))
