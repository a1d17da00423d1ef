"""The dict of registered backends: ``@register_backend("name")`` on a :class:`Backend`
subclass adds it. :func:`splatk.backends.get` reads it (kept apart from the package so that a
backend module registering itself does not import the package that imports it)."""
from __future__ import annotations

from .base import Backend

BACKENDS: dict[str, type[Backend]] = {}


def register_backend(name: str):
    """Class decorator: register a :class:`Backend` subclass as ``name``."""

    def wrap(cls: type[Backend]) -> type[Backend]:
        cls.name = name
        BACKENDS[name] = cls
        return cls

    return wrap
