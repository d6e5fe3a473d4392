"""The shape every factor follows: a pure error function on arrays, wrapped as a GTSAM factor.

A factor module defines ``error(*variables, *measurement) -> (e, [J_1, ...])`` with analytic
Jacobians in GTSAM's tangent coordinates (Pose2: body-frame dx, dy, dtheta), and registers it by
name. ``build`` turns it into a ``gtsam.CustomFactor`` reading its variables from a ``Values``.
"""
from __future__ import annotations

import math
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
        """A ``gtsam.CustomFactor`` on ``keys`` with the measurement bound in."""
        readers = [_READERS[v] for v in self.variables]
        fn = self.error

        def callback(this, values, H):
            xs = [r(values, k) for r, k in zip(readers, keys)]
            e, jac = fn(*xs, *measurement)
            if H is not None:
                for i, j in enumerate(jac):
                    H[i] = j
            return e

        return gtsam.CustomFactor(noise, list(keys), callback)


def _pose(values, key) -> tuple[float, float, float]:
    p = values.atPose2(key)
    return (p.x(), p.y(), p.theta())


_READERS = {"pose": _pose, "vector": lambda values, key: values.atVector(key)}


def register(name: str, variables: tuple[str, ...]):
    """Decorator adding an error function to the registry under ``name``."""

    def deco(fn):
        REGISTRY[name] = FactorKind(name, variables, fn, (fn.__doc__ or "").strip().split("\n")[0])
        return fn

    return deco


def wrap(a: float) -> float:
    """Wrap a scalar angle to (-pi, pi]."""
    w = (a + math.pi) % (2 * math.pi) - math.pi
    return math.pi if w == -math.pi else w
