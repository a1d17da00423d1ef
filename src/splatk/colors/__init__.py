"""Colour models registered by name: ``sh`` (spherical harmonics) and ``sb`` (spherical Beta)."""
from .base import COLOR_MODELS, ColorModel, register_color_model
from . import sh, spherical_beta  # noqa: F401


def make_color_model(name: str, **options) -> ColorModel:
    if name not in COLOR_MODELS:
        raise ValueError(f"unknown colour model {name!r}; choose from {', '.join(sorted(COLOR_MODELS))}")
    return COLOR_MODELS[name](**options)
