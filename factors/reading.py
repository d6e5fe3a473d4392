"""Beacon-reading factor: the raw reading equals the sensor polynomial at the pose-landmark distance."""
from __future__ import annotations

import numpy as np

from .base import pose_jacobian, register


@register("reading", ("pose", "vector"))
def error(p: np.ndarray, c: np.ndarray, landmark: np.ndarray, z: np.ndarray):
    """poly(c, |position - landmark|) - z, with c the coefficients in increasing degree."""
    c = np.broadcast_to(c, (len(p), c.shape[-1]))
    rx, ry = p[:, 0] - landmark[:, 0], p[:, 1] - landmark[:, 1]
    d = np.hypot(rx, ry)
    powers = d[:, None] ** np.arange(c.shape[1])
    f = np.sum(powers * c, axis=1)
    df = np.sum(np.arange(1, c.shape[1]) * powers[:, :-1] * c[:, 1:], axis=1)
    Hxy = pose_jacobian(df * rx / d, df * ry / d, np.cos(p[:, 2]), np.sin(p[:, 2]))
    Hp = np.concatenate([Hxy, np.zeros((len(p), 1))], axis=1)[:, None, :]
    return (f - z)[:, None], [Hp, powers[:, None, :]]
