"""The shape every factor follows: a vectorised error function on arrays, wrapped as a GTSAM factor.

A factor module defines ``error(*variables, *measurements) -> (e, [J_1, ...])`` on batches: each
argument has a leading dimension n, ``e`` is (n, m) and each ``J_i`` is (n, m, dim_i), analytic, in
GTSAM's tangent coordinates (Pose2: body-frame dx, dy, dtheta). The batch form linearises a
whole log in one numpy pass (the hot path); :meth:`FactorKind.build` wraps the same function as
a ``gtsam.CustomFactor`` for GTSAM's own optimizers, marginals and tests.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

REGISTRY: dict[str, "FactorKind"] = {}


@dataclass(frozen=True)
class FactorKind:
    """A registered factor: its name, the variable types it connects, and its error function."""

    name: str
    variables: tuple[str, ...]          # each "pose" (gtsam.Pose2) or "vector"
    error: Callable
    doc: str

    def build(self, noise, keys, *measurement) -> gtsam.CustomFactor:
        """A ``gtsam.CustomFactor`` on ``keys`` with one measurement bound in."""
        readers = [_READERS[v] for v in self.variables]
        fn = self.error
        meas = [np.asarray(m, float)[None] for m in measurement]

        def callback(this, values, H):
            xs = [r(values, k)[None] for r, k in zip(readers, keys)]
            e, jac = fn(*xs, *meas)
            if H is not None:
                for i, j in enumerate(jac):
                    H[i] = j[0]
            return e[0]

        return gtsam.CustomFactor(noise, list(keys), callback)


def _pose(values, key) -> np.ndarray:
    p = values.atPose2(key)
    return np.array([p.x(), p.y(), p.theta()])


_READERS = {"pose": _pose, "vector": lambda values, key: np.asarray(values.atVector(key), float)}


def register(name: str, variables: tuple[str, ...]):
    """Decorator adding an error function to the registry under ``name``."""

    def deco(fn):
        REGISTRY[name] = FactorKind(name, variables, fn, (fn.__doc__ or "").strip().split("\n")[0])
        return fn

    return deco


def wrap(a):
    """Wrap angles to (-pi, pi]."""
    w = np.mod(np.asarray(a, float) + np.pi, 2 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def relative(a: np.ndarray, b: np.ndarray):
    """Body-frame displacement of pose b from pose a, with its derivatives in GTSAM tangent space."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    dx, dy = c * ex + s * ey, -s * ex + c * ey
    n = len(a)
    Ha = np.zeros((n, 3, 3))
    Ha[:, 0, 0] = Ha[:, 1, 1] = Ha[:, 2, 2] = -1.0
    Ha[:, 0, 2], Ha[:, 1, 2] = dy, -dx
    rel = b[:, 2] - a[:, 2]
    cr, sr = np.cos(rel), np.sin(rel)
    Hb = np.zeros((n, 3, 3))
    Hb[:, 0, 0], Hb[:, 0, 1], Hb[:, 1, 0], Hb[:, 1, 1], Hb[:, 2, 2] = cr, -sr, sr, cr, 1.0
    return np.column_stack([dx, dy, rel]), Ha, Hb


def pose_jacobian(gx, gy, cos_th, sin_th) -> np.ndarray:
    """(n, 2) derivative of a function of world position with gradient (gx, gy) w.r.t. a body-frame step."""
    return np.stack([gx * cos_th + gy * sin_th, -gx * sin_th + gy * cos_th], axis=-1)
