"""Action-table factor: the displacement between two poses equals the action's velocity held for k steps."""
from __future__ import annotations

import numpy as np

from .base import register, relative, wrap


def displacement(v: np.ndarray, k: np.ndarray, dt: np.ndarray):
    """Predicted (dx, dy, dtheta) in the start frame after ``k`` steps of the paper's additive model.

    Each step adds R(theta_j) v dt with theta_j = theta_0 + j w dt, so the sum is exact:
    dt * G (vx, vy) with G = sum_{j<k} R(j w dt) = a I + b J, (a + i b) a geometric series.
    Returns (n, 3) displacements and their (n, 3, 3) derivative with respect to v.
    """
    v = np.atleast_2d(np.asarray(v, float))
    k = np.broadcast_to(np.asarray(k, float), v.shape[:1])
    dt = np.broadcast_to(np.asarray(dt, float), v.shape[:1])
    phi = v[:, 2] * dt
    kmax = int(k.max(initial=0))
    j = np.arange(kmax)
    mask = j[None, :] < k[:, None]
    ang = j[None, :] * phi[:, None]
    c, s = np.cos(ang) * mask, np.sin(ang) * mask
    a, b = c.sum(1), s.sum(1)
    da, db = -(j * s).sum(1), (j * c).sum(1)          # d/dphi of a and b
    vx, vy = v[:, 0], v[:, 1]
    d = np.column_stack([dt * (a * vx - b * vy), dt * (b * vx + a * vy), k * phi])
    J = np.zeros((len(v), 3, 3))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = dt * a, -dt * b, dt * dt * (da * vx - db * vy)
    J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = dt * b, dt * a, dt * dt * (db * vx + da * vy)
    J[:, 2, 2] = k * dt
    return d, J


@register("action", ("pose", "pose", "vector"))
def error(a: np.ndarray, b: np.ndarray, v: np.ndarray, k: np.ndarray, dt: np.ndarray):
    """Body-frame displacement from pose a to pose b minus the velocity v held for k steps of dt."""
    rel, Ha, Hb = relative(a, b)
    pred, Jv = displacement(v, k, dt)
    e = np.column_stack([rel[:, 0] - pred[:, 0], rel[:, 1] - pred[:, 1], wrap(rel[:, 2] - pred[:, 2])])
    return e, [Ha, Hb, -Jv]
