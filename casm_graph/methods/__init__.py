"""Calibration methods, one module each, looked up by name (``--method``)."""
from .base import METHODS, Fit, Progress, register
from . import graph  # noqa: F401  (registers "graph")

__all__ = ["METHODS", "Fit", "Progress", "register"]
