"""GTSAM factors of casm-graph, registered by name: ``factors.REGISTRY["action"].build(...)``."""
from . import action, bearing, reading  # noqa: F401  (importing registers them)
from .base import REGISTRY, FactorKind, register

__all__ = ["REGISTRY", "FactorKind", "register"]
