"""The shape every calibration method follows, and the registry ``--method`` looks names up in."""
from __future__ import annotations

from typing import Callable

from casm_graph.fit.result import Fit, Progress

__all__ = ["METHODS", "Fit", "Progress", "register"]

METHODS: dict[str, Callable[..., Fit]] = {}


def register(name: str):
    """Decorator adding ``fit(log, start, seed, progress) -> Fit`` to the registry under ``name``."""

    def deco(fn):
        METHODS[name] = fn
        return fn

    return deco
