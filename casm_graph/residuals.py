"""Residuals of a fitted model on its log, per channel, as plain arrays.

Channels follow INTERFACE section 4: ``forward``, ``lateral``, ``turn`` (motion residuals in the
body frame of each segment's start pose, per step of the segment) and ``reading``, ``bearing``.
"""
from __future__ import annotations

import numpy as np

from .graph import Layout
from .log import Log, wrap
from .model import Model


def displacement(v: np.ndarray, k: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """(n, 3) predicted start-frame displacement of velocities ``v`` (n, 3) held for ``k`` steps of ``dt``.

    Vectorised twin of :func:`factors.action.displacement` (sum_j R(j w dt) v dt, exact).
    """
    k = np.asarray(k, float)
    phi = v[:, 2] * dt
    z = np.exp(1j * phi)
    small = np.abs(phi) < 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        geo = np.where(small, k, (1 - z ** k) / np.where(small, 1.0, 1 - z))
    a, b = geo.real, geo.imag
    return np.column_stack([dt * (a * v[:, 0] - b * v[:, 1]), dt * (b * v[:, 0] + a * v[:, 1]), k * phi])


def motion(poses: np.ndarray, lay: Layout, model: Model) -> np.ndarray:
    """(K-1, 3) measured minus predicted displacement between consecutive knots, start body frame."""
    a, b = poses[:-1], poses[1:]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    meas = np.column_stack([c * ex + s * ey, -s * ex + c * ey, b[:, 2] - a[:, 2]])
    pred = displacement(model.velocities[lay.seg_action], lay.seg_steps, lay.seg_dt)
    r = meas - pred
    r[:, 2] = wrap(r[:, 2])
    return r


def observation(poses_at_obs: np.ndarray, log: Log, model: Model) -> tuple[np.ndarray, np.ndarray]:
    """Reading and bearing residuals (measured minus predicted; NaN where not measured)."""
    lm = log.landmark_xy[log.landmark_index]
    rel = lm - poses_at_obs[:, :2]
    d = np.hypot(rel[:, 0], rel[:, 1])
    reading = log.obs_reading - model.reading(d)
    bearing = wrap(log.obs_bearing - (np.arctan2(rel[:, 1], rel[:, 0]) - poses_at_obs[:, 2]))
    return reading, bearing


def distances(poses_at_obs: np.ndarray, log: Log) -> np.ndarray:
    """Distance from each observation's pose to its landmark."""
    rel = log.landmark_xy[log.landmark_index] - poses_at_obs[:, :2]
    return np.hypot(rel[:, 0], rel[:, 1])
