"""actuator_lag: after an action change the velocity approaches the new one with a time constant.

A family by the drive's stages: order 1 one first-order stage (an exponential approach), order 2 two equal
stages in cascade (a critically damped drive: the velocity leaves the old one slowly, then settles); both have
the one parameter ``tau``, so BIC compares them by their fit alone. The action before is taken as settled.

On an action table the lag acts through the ``velocity`` hook, per step since the action changed; a command map
holds its mean delay and order and runs its basis through :func:`lagged` (a continuous command changes every
step), which keeps the map linear in its coefficients."""
from __future__ import annotations

import numpy as np
from numba import njit

from casm_graph.models.effects.base import Effect, register

MIN_TAU = 1e-3


@njit(cache=True)
def _first_order(x: np.ndarray, a: np.ndarray, g: np.ndarray) -> np.ndarray:
    """One first-order stage over rows ``x``: each row out the stage's mean over its step (``g``), ``a`` its decay."""
    y = np.empty_like(x)
    y[0] = x[0]
    end = x[0].copy()
    for k in range(1, x.shape[0]):
        y[k] = x[k] + (end - x[k]) * g[k]
        end = a[k] * end + (1.0 - a[k]) * x[k]
    return y


def lagged(x: np.ndarray, dt: np.ndarray, lag: float, order: int = 1) -> np.ndarray:
    """Rows of ``x`` (one per step, held over it) through ``order`` cascaded first-order lags of time constant
    ``lag / order`` (mean delay ``lag``), from rest at x[0]: each row out is the lag's mean over its step, as
    the step's displacement needs (the value at the step's end would lead the motion by half a step per stage)."""
    if lag <= 0:
        return x
    r = np.asarray(dt, float) * order / lag
    a = np.exp(-r)
    g = np.where(r > 1e-9, -np.expm1(-r) / np.maximum(r, 1e-300), 1.0)    # mean of exp(-t / tau) over the step
    y = np.ascontiguousarray(x, dtype=float)
    for _ in range(order):
        y = _first_order(y, a, g)
    return y


def _still_held(u0, u1, order: int):
    """The share of an old velocity a lag of ``order`` equal stages still holds, exp(-u) for one stage and
    (1 + u) exp(-u) for two, integrated from u0 to u1 (times in units of a stage's time constant)."""
    if order == 2:
        return (2 + u0) * np.exp(-u0) - (2 + u1) * np.exp(-u1)
    return np.exp(-u0) - np.exp(-u1)


def memory(dt: np.ndarray, lag: float, order: int = 1) -> np.ndarray:
    """(T,) displacement over each step of durations ``dt`` per unit of velocity offset the lag held when the log
    began, as its ``order`` stages of mean delay ``lag`` forget it: order 1 exp(-t/a), order 2 (1 + t/a) exp(-t/a),
    a = lag / order, integrated over the step."""
    t1 = np.cumsum(np.asarray(dt, float))
    if lag <= 0:
        return np.zeros_like(t1)
    a = lag / order
    return a * _still_held(np.concatenate([[0.0], t1[:-1]]) / a, t1 / a, order)


@register
class ActuatorLag(Effect):
    name = "actuator_lag"
    scale_free = True
    channel = "motion"
    params = ("tau",)
    start = (0.005,)
    scale = (0.01,)
    orders = (1, 2)                  # first-order stages in cascade
    order = 1
    explains = (("forward", "time_since_action_change"), ("lateral", "time_since_action_change"),
                ("turn", "time_since_action_change"), ("forward", "acceleration"), ("turn", "turn_acceleration"))
    signature = "correlation"
    distinguished_by = ("commands that change faster than the lag, with sightings just after each change: the "
                        "body's motion trails the command, while a camera latency shifts only what the camera "
                        "sees")
    physics = ("The gait cannot switch instantly: after each new command the body keeps some of the "
               "old motion and settles to the new velocity exponentially with time constant tau (order 2: "
               "through two such stages, a critically damped drive).")

    @staticmethod
    def start_memory(entry: dict, dt: np.ndarray) -> np.ndarray:
        """(T,) displacement over each step per unit of velocity offset held from before the log, for the lag a
        model.json entry records (``tau`` a stage's time constant, ``order`` its stages): :func:`memory` at its mean
        delay; zeros without a delay."""
        order = int(entry.get("order") or 1)
        return memory(dt, abs(entry.get("tau", 0.0)) * order, order)

    def velocity(self, theta, v, ctx):
        tau = max(abs(theta[0]), MIN_TAU)
        a, b = ctx["since"] / tau, (ctx["since"] + ctx["dt"]) / tau
        g = _still_held(a, b, self.order) / (b - a)        # the old velocity's mean share over the step
        return v + (ctx["v_prev"] - v) * g[:, None]
