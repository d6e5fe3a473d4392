"""Calibration methods, one module each, looked up by name (``--method``)."""
from casm_graph.fit.methods import (
    ekfs_em,  # noqa: F401  (each registers itself)
    graph,  # noqa: F401  (each registers itself)
    graph_em,  # noqa: F401  (each registers itself)
)
from casm_graph.fit.methods.base import METHODS, Fit, Progress, register

__all__ = ["METHODS", "Fit", "Progress", "register"]
