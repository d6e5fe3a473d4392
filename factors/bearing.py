"""Bearing factor: the landmark's direction relative to the body heading equals the measured bearing."""
from __future__ import annotations

import numpy as np

from .base import pose_jacobian, register, wrap


@register("bearing", ("pose",))
def error(p: np.ndarray, landmark: np.ndarray, z: np.ndarray):
    """wrap(atan2(landmark - position) - heading - z)."""
    rx, ry = landmark[:, 0] - p[:, 0], landmark[:, 1] - p[:, 1]
    r2 = rx * rx + ry * ry
    e = wrap(np.arctan2(ry, rx) - p[:, 2] - z)
    Hxy = pose_jacobian(ry / r2, -rx / r2, np.cos(p[:, 2]), np.sin(p[:, 2]))
    Hp = np.concatenate([Hxy, -np.ones((len(p), 1))], axis=1)[:, None, :]
    return e[:, None], [Hp]
