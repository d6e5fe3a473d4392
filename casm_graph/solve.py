"""Levenberg-Marquardt driven from Python: linearise a Python-owned ``Values``, solve, retract, damp.

GTSAM's stock optimizers copy the whole ``Values`` into Python on every ``CustomFactor`` call;
driving the iterations here keeps each linearisation one pass over the factors.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np


@dataclass
class History:
    """Cost (GTSAM error = half the whitened squared residual) after each accepted iteration."""

    cost: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False


def _damping(keys_dims, lam: float) -> gtsam.GaussianFactorGraph:
    g = gtsam.GaussianFactorGraph()
    s = np.sqrt(lam)
    for key, dim in keys_dims:
        g.add(gtsam.JacobianFactor(key, s * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim)))
    return g


def least_squares(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, ordering: gtsam.Ordering,
                  max_iterations: int = 30, rel_tol: float = 1e-6, lam: float = 1e-6,
                  history: History | None = None, on_iteration=None) -> tuple[gtsam.Values, History]:
    """Minimise ``graph.error`` from ``values``; returns the new values and the cost history."""
    hist = history if history is not None else History()
    zero = values.zeroVectors()
    keys_dims = [(k, len(zero.at(k))) for k in values.keys()]
    cost = graph.error(values)
    if not hist.cost:
        hist.cost.append(cost)
    for _ in range(max_iterations):
        lin = graph.linearize(values)
        while True:
            system = lin.clone()
            if lam > 0:
                system.push_back(_damping(keys_dims, lam))
            delta = system.optimize(ordering) if ordering is not None else system.optimize()
            trial = values.retract(delta)
            new_cost = graph.error(trial)
            if np.isfinite(new_cost) and new_cost <= cost:
                lam = max(lam / 10.0, 1e-9) if lam > 0 else 0.0
                break
            lam = max(lam * 10.0, 1e-6)
            if lam > 1e8:
                hist.converged = True
                return values, hist
        improvement = (cost - new_cost) / max(cost, 1e-300)
        values, cost = trial, new_cost
        hist.cost.append(cost)
        hist.iterations += 1
        if on_iteration is not None:
            on_iteration(cost)
        if improvement < rel_tol:
            hist.converged = True
            break
    return values, hist

