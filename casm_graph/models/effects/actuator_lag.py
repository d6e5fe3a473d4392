"""actuator_lag: after an action change the velocity approaches the new one with a time constant."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register

MIN_TAU = 1e-3


@register
class ActuatorLag(Effect):
    name = "actuator_lag"
    channel = "motion"
    params = ("tau",)
    start = (0.005,)
    scale = (0.01,)
    explains = (("forward", "time_since_action_change"), ("lateral", "time_since_action_change"),
                ("turn", "time_since_action_change"), ("forward", "acceleration"), ("turn", "turn_acceleration"))
    distinguished_by = ("commands that change faster than the lag, with sightings just after each change: the "
                        "body's motion trails the command, while a camera latency shifts only what the camera "
                        "sees")
    physics = ("The gait cannot switch instantly: after each new command the body keeps some of the "
               "old motion and settles to the new velocity exponentially with time constant tau.")

    def velocity(self, theta, v, ctx):
        tau = max(abs(theta[0]), MIN_TAU)
        s, dt = ctx["since"], ctx["dt"]
        g = tau / dt * (np.exp(-s / tau) - np.exp(-(s + dt) / tau))   # mean of exp(-t/tau) over the step
        return v + (ctx["v_prev"] - v) * g[:, None]
