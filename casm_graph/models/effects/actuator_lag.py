"""actuator_lag: after an action change the velocity approaches the new one with a time constant.

A family by the drive's stages: order 1 one first-order stage (an exponential approach), order 2 two equal
stages in cascade (a critically damped drive: the velocity leaves the old one slowly, then settles); both have
the one parameter ``tau``, so BIC compares them by their fit alone. The action before is taken as settled."""
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
    orders = (1, 2)                  # first-order stages in cascade
    order = 1
    explains = (("forward", "time_since_action_change"), ("lateral", "time_since_action_change"),
                ("turn", "time_since_action_change"), ("forward", "acceleration"), ("turn", "turn_acceleration"))
    distinguished_by = ("commands that change faster than the lag, with sightings just after each change: the "
                        "body's motion trails the command, while a camera latency shifts only what the camera "
                        "sees")
    physics = ("The gait cannot switch instantly: after each new command the body keeps some of the "
               "old motion and settles to the new velocity exponentially with time constant tau (order 2: "
               "through two such stages, a critically damped drive).")

    def velocity(self, theta, v, ctx):
        tau = max(abs(theta[0]), MIN_TAU)
        a, b = ctx["since"] / tau, (ctx["since"] + ctx["dt"]) / tau
        if self.order == 2:           # mean over the step of the old velocity's share (1 + t/tau) exp(-t/tau)
            g = ((2 + a) * np.exp(-a) - (2 + b) * np.exp(-b)) / (b - a)
        else:                         # mean of exp(-t/tau) over the step
            g = (np.exp(-a) - np.exp(-b)) / (b - a)
        return v + (ctx["v_prev"] - v) * g[:, None]
