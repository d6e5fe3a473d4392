"""battery_fade: every velocity shrinks in proportion to the time the robot has been running."""
from __future__ import annotations

from casm_graph.models.effects.base import Effect, register


@register
class BatteryFade(Effect):
    name = "battery_fade"
    channel = "motion"
    params = ("loss_per_minute",)
    start = (0.0,)
    scale = (0.005,)
    explains = (("forward", "time"), ("lateral", "time"), ("turn", "time"))
    distinguished_by = ("the same actions run early and late in every part of the field: a fading battery slows "
                        "the robot when it is, a slow floor where it is")
    physics = ("As the battery drains the servos deliver less power, so every action runs slower "
               "the longer the robot has been on: velocities fall by a fixed fraction per minute.")

    def velocity(self, theta, v, ctx):
        return v * (1.0 - theta[0] * ctx["t"] / 60.0)[:, None]
