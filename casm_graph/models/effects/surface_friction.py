"""surface_friction: a region of the field (e.g. a carpet) slows the robot down."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register

EDGE = 0.1   # m, width of the smooth step between regions


def side(u):
    """Smooth 0 -> 1 step across u = 0."""
    return 0.5 * (1.0 + np.tanh(u / EDGE))


@register
class SurfaceFriction(Effect):
    name = "surface_friction"
    channel = "motion"
    params = ("slow_east", "slow_north")
    start = (0.0, 0.0)
    scale = (0.02, 0.02)
    explains = (("forward", "x"), ("forward", "y"), ("lateral", "x"), ("lateral", "y"),
                ("turn", "x"), ("turn", "y"))
    distinguished_by = ("the same actions run in every part of the field early and late: a slow floor slows the "
                        "robot where it is, a fading battery when it is")
    physics = ("The floor is not uniform: on one part of the field (x > 0 or y > 0) the feet slip or "
               "drag, so every action covers a smaller fraction of its usual distance there.")

    def velocity(self, theta, v, ctx):
        x, y = ctx["pose"][:, 0], ctx["pose"][:, 1]
        f = (1.0 - theta[0] * side(x)) * (1.0 - theta[1] * side(y))
        return v * f[:, None]

    def simulate_params(self, value, rng):
        return np.array([value, 0.0])
