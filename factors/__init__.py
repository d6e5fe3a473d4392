"""GTSAM factors of casm-graph, registered by name: ``factors.REGISTRY["action"].build(...)``."""
from . import action, bearing, command, effect_motion, effect_sighting, reading, standoff  # noqa: F401  (registers)
from .base import REGISTRY, FactorKind, register

__all__ = ["REGISTRY", "FactorKind", "register"]
