"""The effect catalog (INTERFACE section 6): one module per physical effect, a registry by name.

Write your own by subclassing :class:`Effect` and decorating it with :func:`register`; see the
README section "Add your own effect".
"""
from . import (actuator_lag, battery_fade, camera_latency, false_detections,  # noqa: F401
               landmark_offset, lens_distortion, range_dependent_noise, regional_motion_noise, surface_friction)
from .base import REGISTRY, Effect, get, register

__all__ = ["REGISTRY", "Effect", "get", "register", "catalog"]


def catalog() -> list[dict]:
    """Name, channel, parameters and physics of every registered effect."""
    out = []
    for name in sorted(REGISTRY):
        e = REGISTRY[name]()
        out.append({"name": name, "channel": e.channel, "parameters": list(e.params),
                    "physics": e.physics})
    return out
