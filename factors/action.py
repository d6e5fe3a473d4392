"""Action-table factor: the displacement between two poses equals the action's velocity held for k steps."""
from __future__ import annotations

import math

import numpy as np

from .base import register, wrap


def displacement(v: np.ndarray, k: int, dt: float):
    """Predicted (dx, dy, dtheta) in the start frame after ``k`` steps of the paper's additive model.

    Each step adds R(theta_j) v dt with theta_j = theta_0 + j w dt, so the sum is exact:
    dt * G(k, w dt) (vx, vy) with G = sum_j R(j w dt). Returns the displacement and d/dv (3x3).
    """
    vx, vy, w = float(v[0]), float(v[1]), float(v[2])
    phi = w * dt
    if k == 1:
        a, b, da, db = 1.0, 0.0, 0.0, 0.0
    else:
        j = np.arange(k)
        c, s = np.cos(j * phi), np.sin(j * phi)
        a, b, da, db = c.sum(), s.sum(), -(j * s).sum(), (j * c).sum()
    d = np.array([dt * (a * vx - b * vy), dt * (b * vx + a * vy), k * phi])
    J = np.array([[dt * a, -dt * b, dt * dt * (da * vx - db * vy)],
                  [dt * b, dt * a, dt * dt * (db * vx + da * vy)],
                  [0.0, 0.0, k * dt]])
    return d, J


@register("action", ("pose", "pose", "vector"))
def error(a: np.ndarray, b: np.ndarray, v: np.ndarray, k: int, dt: float):
    """Body-frame displacement from pose a to pose b minus the velocity v held for k steps of dt."""
    ax, ay, ath = a
    bx, by, bth = b
    c, s = math.cos(ath), math.sin(ath)
    ex, ey = bx - ax, by - ay
    dx, dy = c * ex + s * ey, -s * ex + c * ey
    pred, Jv = displacement(v, k, dt)
    e = np.array([dx - pred[0], dy - pred[1], wrap(bth - ath - pred[2])])
    Ha = np.array([[-1.0, 0.0, dy], [0.0, -1.0, -dx], [0.0, 0.0, -1.0]])
    cr, sr = math.cos(bth - ath), math.sin(bth - ath)
    Hb = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return e, [Ha, Hb, -Jv]
