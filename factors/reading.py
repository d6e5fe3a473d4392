"""Beacon-reading factor: the raw reading equals the sensor curve at the pose-landmark distance.

The curve is a polynomial in the distance (the paper's) or in the inverse distance (``basis``
"inverse_distance": an apparent size in pixels falls as 1/d, which no low-degree polynomial in d
follows over a range of 20:1). Both are linear in the coefficients.
"""
from __future__ import annotations

import numpy as np

from .base import pose_jacobian, register

BASES = ("distance", "inverse_distance")
NEAREST = 0.05           # m: the inverse distance is taken no closer than this (a pose on a landmark)


def features(d: np.ndarray, n: int, basis: str = "distance") -> tuple[np.ndarray, np.ndarray]:
    """Powers 0..n-1 of the curve's variable at distances ``d`` (the reading's design rows) and their
    derivatives with respect to ``d``; shapes ``d.shape + (n,)``."""
    d = np.asarray(d, float)
    if basis == "distance":
        u, du = d, np.ones_like(d)
    elif basis == "inverse_distance":
        dc = np.maximum(d, NEAREST)
        u, du = 1.0 / dc, np.where(d > NEAREST, -1.0 / dc ** 2, 0.0)
    else:
        raise ValueError(f"unknown sensor curve basis {basis!r} (one of {', '.join(BASES)})")
    k = np.arange(n)
    powers = u[..., None] ** k
    dpowers = np.zeros_like(powers)
    dpowers[..., 1:] = k[1:] * powers[..., :-1] * du[..., None]
    return powers, dpowers


def curve(d: np.ndarray, c: np.ndarray, basis: str = "distance") -> np.ndarray:
    """The sensor curve with coefficients ``c`` (increasing degree) at distances ``d``."""
    if basis == "distance":
        return np.polynomial.polynomial.polyval(np.asarray(d, float), np.asarray(c, float))
    return features(d, len(c), basis)[0] @ np.asarray(c, float)


def slope(d: np.ndarray, c: np.ndarray, basis: str = "distance") -> np.ndarray:
    """The sensor curve's derivative with respect to the distance at ``d``."""
    if basis == "distance":
        return np.polynomial.polynomial.polyval(np.asarray(d, float), np.polynomial.polynomial.polyder(c))
    return features(d, len(c), basis)[1] @ np.asarray(c, float)


def fit_curve(d: np.ndarray, reading: np.ndarray, degree: int, basis: str = "distance") -> np.ndarray:
    """Least-squares coefficients of a degree-``degree`` curve through ``(d, reading)``."""
    if basis == "distance":
        return np.polynomial.polynomial.polyfit(np.asarray(d, float), reading, degree)
    V = features(d, degree + 1, basis)[0]
    scale = np.maximum(np.abs(V).max(axis=0), 1e-300)      # column scaling: powers of d and 1/d span decades
    return np.linalg.lstsq(V / scale, reading, rcond=None)[0] / scale


@register("reading", ("pose", "vector"))
def error(p: np.ndarray, c: np.ndarray, landmark: np.ndarray, z: np.ndarray, basis: str = "distance"):
    """curve(c, |position - landmark|) - z, with c the coefficients in increasing degree."""
    c = np.broadcast_to(c, (len(p), c.shape[-1]))
    rx, ry = p[:, 0] - landmark[:, 0], p[:, 1] - landmark[:, 1]
    d = np.hypot(rx, ry)
    powers, dpowers = features(d, c.shape[1], basis)
    f = np.sum(powers * c, axis=1)
    df = np.sum(dpowers * c, axis=1)
    dsafe = np.maximum(d, 1e-12)
    Hxy = pose_jacobian(df * rx / dsafe, df * ry / dsafe, np.cos(p[:, 2]), np.sin(p[:, 2]))
    Hp = np.concatenate([Hxy, np.zeros((len(p), 1))], axis=1)[:, None, :]
    return (f - z)[:, None], [Hp, powers[:, None, :]]
