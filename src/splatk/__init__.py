"""splatk: splatting-based novel view synthesis with learned, view-dependent kernels.

The engine (this package) knows nothing of the command line; `splatk_cli` is the thin layer
that parses flags and prints. Layers: data -> models -> functional/kernels/colors -> backends.
"""
from ._malloc import tune_malloc

tune_malloc()

__version__ = "0.1.0"
