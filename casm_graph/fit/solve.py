"""Levenberg-Marquardt driven from Python over a log's graph, and the marginals.

GTSAM's stock optimizers call a ``CustomFactor`` back into Python per factor and copy the whole
``Values`` each time; here each iteration is one numpy pass to linearise, one elimination of the
damped normal equations along the pose chain (:mod:`casm_graph.graph.chain`, the step GTSAM's
multifrontal solve gives, tests/test_marginals_chain.py), and one numpy pass to evaluate the trial. The final marginals
come from a selected inversion of the pose chain and its dense parameter block (:func:`chain_marginals`),
O(length) where ``gtsam.Marginals`` is slow and memory-hungry on a long chain.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from casm_graph.graph.chain import RIDGES, arrow_blocks, arrow_inverse


@dataclass
class History:
    """Cost (GTSAM error = half the whitened squared residual) after each accepted iteration."""

    cost: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False


RIDGE_WARNING = ("the fitted graph is nearly singular (a poor fit or a log that cannot pin the model down): "
                 "standard deviations computed with a ridge of {:g} x the largest information; treat them as lower bounds")


def world_std(poses: np.ndarray, body_std: np.ndarray, body_cov_xy: np.ndarray) -> np.ndarray:
    """Map-frame (sx, sy, stheta) from Pose2 marginals, which live in the body frame (GTSAM's tangent)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    cov = R @ body_cov_xy @ np.transpose(R, (0, 2, 1))
    return np.column_stack([np.sqrt(cov[:, 0, 0]), np.sqrt(cov[:, 1, 1]), body_std[:, 2]])


def _damping(keys_dims, lam: float) -> gtsam.GaussianFactorGraph:
    g = gtsam.GaussianFactorGraph()
    s = np.sqrt(lam)
    for key, dim in keys_dims:
        g.add(key, s * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim))
    return g


NOT_DETERMINED = "the fitted model leaves the trajectory undetermined: no marginals even with a ridge"


def marginals(lin: gtsam.GaussianFactorGraph, keys_dims) -> tuple[gtsam.Marginals, float]:
    """GTSAM marginals of ``lin``; an ill-conditioned system is retried with a tiny ridge.

    Returns the marginals and the ridge used (0 when none was needed), relative to the largest
    diagonal entry of the information matrix, so callers can say the std are regularised.
    """
    try:
        return gtsam.Marginals(lin, gtsam.VectorValues()), 0.0
    except RuntimeError:
        pass
    _, col, val = lin.sparseJacobian_()                   # 1-based (row, column, value); b is the last column
    n = sum(d for _, d in keys_dims)
    keep = col <= n
    top = float(np.bincount(col[keep].astype(int), weights=val[keep] ** 2).max())
    for rel in RIDGES:
        system = lin.clone()
        system.push_back(_damping(keys_dims, rel * top))
        try:
            return gtsam.Marginals(system, gtsam.VectorValues()), rel
        except RuntimeError:
            continue
    raise RuntimeError(NOT_DETERMINED)


class ChainMarginals:
    """Per-pose and parameter covariances of a chain graph, read by key as from ``gtsam.Marginals``.

    ``pose_cov`` (K, 3, 3) is in each pose's tangent (GTSAM's body frame); ``param_cov`` covers the
    non-pose keys of ``keys_dims`` in their order.
    """

    def __init__(self, keys_dims, n_poses: int, pose_cov: np.ndarray, param_cov: np.ndarray):
        self.pose_cov, self.param_cov = pose_cov, param_cov
        self._pose = {k: i for i, (k, _) in enumerate(keys_dims[:n_poses])}
        dims = [d for _, d in keys_dims[n_poses:]]
        offsets = np.concatenate([[0], np.cumsum(dims)]).astype(int)
        self._param = {k: slice(int(o), int(o) + d) for (k, d), o in zip(keys_dims[n_poses:], offsets)}

    def marginalCovariance(self, key) -> np.ndarray:
        if key in self._pose:
            return self.pose_cov[self._pose[key]]
        s = self._param[key]
        return self.param_cov[s, s]


def chain_marginals(problem, st) -> tuple[ChainMarginals, float]:
    """Marginals of ``problem`` (a pose chain and a dense parameter block, with ``jacobian``, ``keys_dims`` and
    ``lay.n_poses``) linearised at ``st``, by :func:`arrow_inverse`: the same numbers as :func:`marginals`
    in O(length). A singular system is retried with the same ridges; returns the ridge used (0: none).
    """
    K = problem.lay.n_poses
    blocks = arrow_blocks(problem.jacobian(st)[0], K)
    for rel in (0.0, *RIDGES):
        try:
            pose_cov, param_cov = arrow_inverse(blocks, rel * blocks["top"])
        except np.linalg.LinAlgError:
            continue
        return ChainMarginals(problem.keys_dims(), K, pose_cov, param_cov), rel
    raise RuntimeError(NOT_DETERMINED)


def least_squares(problem, st, max_iterations: int = 30, rel_tol: float = 1e-6, lam: float = 1e-6,
                  on_iteration=None, freeze_parameters: bool = False):
    """Minimise ``problem.cost`` from ``st``; returns the new state and the cost history.

    ``problem`` is a graph with ``cost``, ``normal_equations``, ``solve_damped`` and ``retract`` (the pose
    chain eliminated directly, then the dense parameter block: :mod:`casm_graph.graph.chain`).
    ``freeze_parameters`` holds the parameters where they are (poses only).
    """
    hist = History()
    cost = problem.cost(st)
    hist.cost.append(cost)
    for _ in range(max_iterations):
        neq = problem.normal_equations(st, poses_only=freeze_parameters)
        while True:
            try:
                trial = problem.retract(st, problem.solve_damped(neq, lam))
            except np.linalg.LinAlgError:       # singular at this damping (cancellation in the chain): damp more
                trial = None
            new_cost = problem.cost(trial) if trial is not None else np.inf
            if np.isfinite(new_cost) and new_cost <= cost:
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e8:
                hist.converged = True
                return st, hist
        improvement = (cost - new_cost) / max(cost, 1e-300)
        st, cost = trial, new_cost
        hist.cost.append(cost)
        hist.iterations += 1
        if on_iteration is not None:
            on_iteration(cost)
        if improvement < rel_tol:
            hist.converged = True
            break
    return st, hist
