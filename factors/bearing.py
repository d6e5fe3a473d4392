"""Bearing factor: the landmark's direction relative to the body heading equals the measured bearing."""
from __future__ import annotations

import math

import numpy as np

from .base import register, wrap


@register("bearing", ("pose",))
def error(p: np.ndarray, landmark: np.ndarray, z: float):
    """wrap(atan2(landmark - position) - heading - z)."""
    rx, ry = landmark[0] - p[0], landmark[1] - p[1]
    r2 = rx * rx + ry * ry
    e = wrap(math.atan2(ry, rx) - p[2] - z)
    gx, gy = ry / r2, -rx / r2
    cs, sn = math.cos(p[2]), math.sin(p[2])
    return np.array([e]), [np.array([[gx * cs + gy * sn, -gx * sn + gy * cs, -1.0]])]
