"""splatk: splatting-based novel view synthesis with learned, view-dependent kernels.

The engine (this package) knows nothing of the command line; `splatk_cli` is the thin layer
that parses flags and prints. Layers: data -> models -> functional/kernels/colors -> backends.
Importing it changes no process-wide state: the malloc tuning training wants
(:func:`splatk._malloc.tune_malloc`) is the `splatk` command's to make, or a script's.
"""
__version__ = "0.1.0"
