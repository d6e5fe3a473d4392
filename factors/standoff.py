"""Standoff: a landmark is sighted from outside it, no closer than ``STANDOFF`` to its centre.

A bearing (or a reading in 1/d) from a pose sitting on its landmark can take any value for a
millimetre's move, so a loosely held trajectory can park a pose there to explain a stray sighting,
and the pose's information then blows up (a bearing's Jacobian is 1/d). This one-sided hinge, zero
beyond ``STANDOFF``, keeps every sighting's pose out of that singularity; a sane fit never feels it.
"""
from __future__ import annotations

import numpy as np

from .base import pose_jacobian

STANDOFF = 0.05          # m: no sighting from closer than this to the landmark's centre (as factors.reading.NEAREST)
SIGMA = 0.01             # m: the hinge's stiffness


def error(p: np.ndarray, landmark: np.ndarray):
    """max(0, STANDOFF - |position - landmark|) / SIGMA and its (n, 3) body-frame pose Jacobian."""
    rx, ry = p[:, 0] - landmark[:, 0], p[:, 1] - landmark[:, 1]
    d = np.hypot(rx, ry)
    inside = d < STANDOFF
    e = np.where(inside, (STANDOFF - d) / SIGMA, 0.0)
    g = np.where(inside, -1.0 / (SIGMA * np.maximum(d, 1e-12)), 0.0)
    Hxy = pose_jacobian(g * rx, g * ry, np.cos(p[:, 2]), np.sin(p[:, 2]))
    return e, np.concatenate([Hxy, np.zeros((len(p), 1))], axis=1)
