"""Calibration methods, one module each, looked up by name (``--method``)."""
from .base import METHODS, Fit, Progress, register
from . import ekfs_em, graph, graph_em  # noqa: F401  (each registers itself)

__all__ = ["METHODS", "Fit", "Progress", "register"]
