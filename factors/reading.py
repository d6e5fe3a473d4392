"""Beacon-reading factor: the raw reading equals the sensor polynomial at the pose-landmark distance."""
from __future__ import annotations

import math

import numpy as np

from .base import register


@register("reading", ("pose", "vector"))
def error(p: np.ndarray, c: np.ndarray, landmark: np.ndarray, z: float):
    """poly(c, |position - landmark|) - z, with c the coefficients in increasing degree."""
    rx, ry = p[0] - landmark[0], p[1] - landmark[1]
    d = math.hypot(rx, ry)
    powers = d ** np.arange(len(c))
    f = float(powers @ c)
    df = float((np.arange(1, len(c)) * powers[:-1]) @ c[1:])
    cs, sn = math.cos(p[2]), math.sin(p[2])
    gx, gy = df * rx / d, df * ry / d
    Hp = np.array([[gx * cs + gy * sn, -gx * sn + gy * cs, 0.0]])
    return np.array([f - z]), [Hp, powers[None, :]]
