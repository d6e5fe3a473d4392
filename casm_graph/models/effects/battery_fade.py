"""battery_fade: every velocity shrinks as the robot keeps running.

A polynomial in time: order 1 loses a fixed fraction per minute, order 2 adds a term in minutes squared (a
battery whose voltage sags faster as it empties); the diagnosis keeps the member BIC prefers."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register


@register
class BatteryFade(Effect):
    name = "battery_fade"
    scale_free = True
    channel = "motion"
    params = ("loss_per_minute",)
    start = (0.0,)
    scale = (0.005,)
    orders = (1, 2)
    order = 1
    regain_share = 0.5    # a fit may regain at most this share of its deepest loss by the log's end
    explains = (("forward", "time"), ("lateral", "time"), ("turn", "time"))
    signature = "speed"
    distinguished_by = ("the same actions run early and late in every part of the field: a fading battery slows "
                        "the robot when it is, a slow floor where it is")
    physics = ("As the battery drains the servos deliver less power, so every action runs slower "
               "the longer the robot has been on: velocities fall by a fixed fraction per minute (order 2: a "
               "quadratic in time, the sag bending as the battery empties).")

    def set_order(self, order: int) -> None:
        super().set_order(order)
        self.params = ("loss_per_minute", "loss_per_minute_squared")[:order]
        self.start, self.scale = (0.0,) * order, (0.005, 0.0005)[:order]

    def implausible(self, theta):
        """A battery only loses charge: a fit that has the robot faster at the log's end than at its start, or
        regaining more than ``regain_share`` of the speed it had lost at its slowest, follows something else (a slow
        floor the robot crosses early in the log; the slip's wander, which an effect-free omni log's quadratic
        followed down 2.5 % and back up 2.1 %)."""
        if self.log is None or len(self.log.pose_times) < 2:
            return None
        span = (self.log.pose_times[-1] - self.log.pose_times[0]) / 60.0
        end = remaining(theta, span)
        if end > 1.0:
            return (f"the robot would run {100 * (end - 1.0):.1f} % faster at the log's end than at its start, "
                    "where a battery only loses charge")
        m = np.linspace(0.0, span, 241)
        r = remaining(theta, m)
        low = int(np.argmin(r))
        if end - r[low] > self.regain_share * (1.0 - r[low]):
            return (f"the robot would lose {100 * (1.0 - r[low]):.1f} % of its speed by minute {m[low]:.1f} and "
                    f"regain {100 * (end - r[low]):.1f} % by the log's end, where a battery only loses charge")
        return None

    def velocity(self, theta, v, ctx):
        return v * remaining(theta, ctx["t"] / 60.0)[:, None]


def remaining(theta, minutes):
    """The share of its speed the robot keeps after ``minutes`` of running: ``1 - m (a + b m)``."""
    m = np.asarray(minutes, float)
    return 1.0 - m * np.polyval(np.asarray(theta, float)[::-1], m)
