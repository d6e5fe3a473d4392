"""Marginal covariances of a pose chain with the parameters held fixed, by block-tridiagonal selected inversion.

With the table and polynomial fixed, action factors link only consecutive poses and sightings
touch one pose each, so the Gauss-Newton information matrix is block tridiagonal (3x3 blocks).
A forward block elimination and a backward pass (the Rauch-Tung-Striebel recursion) give every
pose's covariance, the cross-covariance of consecutive poses and log det H in O(K), where one
``gtsam.Marginals.jointMarginalCovariance`` call per pair costs milliseconds.
Coordinates are GTSAM's Pose2 tangent (body-frame dx, dy, dtheta), as in the factors.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from casm_graph.graph.table import Problem, State


def information_blocks(problem: Problem, st: State) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal (K, 3, 3) and upper off-diagonal (K-1, 3, 3) blocks of J^T J over the poses."""
    r = problem.rows(st)
    K = problem.lay.n_poses
    Ha, Hb, _ = r.action_J
    D = np.zeros((K, 3, 3))
    D[:-1] += np.einsum("nki,nkj->nij", Ha, Ha)
    D[1:] += np.einsum("nki,nkj->nij", Hb, Hb)
    B = np.einsum("nki,nkj->nij", Ha, Hb)
    np.add.at(D, problem.r_knot, np.einsum("ni,nj->nij", r.reading_J[0], r.reading_J[0]))
    np.add.at(D, problem.b_knot, np.einsum("ni,nj->nij", r.bearing_J, r.bearing_J))
    return D, B


@njit(cache=True)
def select_inverse(D, B):
    """(Sigma_ii, Sigma_i,i+1, log det H) of the block-tridiagonal H with blocks D (diag) and B (upper)."""
    K = D.shape[0]
    S = np.empty_like(D)
    Sinv = np.empty_like(D)
    logdet = 0.0
    S[0] = D[0]
    for i in range(K):
        if i > 0:
            S[i] = D[i] - B[i - 1].T @ Sinv[i - 1] @ B[i - 1]
        Sinv[i] = np.linalg.inv(S[i])
        logdet += np.log(np.linalg.det(S[i]))
    cov = np.empty_like(D)
    cross = np.empty_like(B)
    cov[K - 1] = Sinv[K - 1]
    for i in range(K - 2, -1, -1):
        G = Sinv[i] @ B[i]
        cross[i] = -G @ cov[i + 1]
        cov[i] = Sinv[i] + G @ cov[i + 1] @ G.T
        cov[i] = 0.5 * (cov[i] + cov[i].T)
    return cov, cross, logdet


@njit(cache=True)
def _chain_solve(D, B, R, lam):
    """H^-1 R for the block-tridiagonal H = blocks (D + lam I, B) and many right-hand sides R (K, 3, m)."""
    K = D.shape[0]
    Sinv = np.empty_like(D)
    Y = np.empty_like(R)
    eye = np.eye(3) * lam
    for i in range(K):
        S = D[i] + eye
        Y[i] = R[i]
        if i > 0:
            G = np.ascontiguousarray(B[i - 1].T) @ Sinv[i - 1]
            S = S - G @ B[i - 1]
            Y[i] = Y[i] - G @ Y[i - 1]
        Sinv[i] = np.linalg.inv(S)
    Xs = np.empty_like(R)
    Xs[K - 1] = Sinv[K - 1] @ Y[K - 1]
    for i in range(K - 2, -1, -1):
        Xs[i] = Sinv[i] @ (Y[i] - B[i] @ Xs[i + 1])
    return Xs


def solve_arrow(D, B, F, gp, Htt, gt, lam):
    """Solve [[Hpp + lam I, F], [F^T, Htt + lam I]] [dp; dt] = -[gp; gt] with Hpp block tridiagonal.

    ``D`` (K,3,3) and ``B`` (K-1,3,3) are Hpp's blocks, ``F`` (K,3,n) the pose-parameter coupling.
    Eliminates the pose chain first (as GTSAM does with the parameters ordered last), then solves
    the dense Schur complement on the parameters.
    """
    n = F.shape[2]
    R = np.concatenate([gp[:, :, None], F], axis=2)
    Xs = _chain_solve(D, B, np.ascontiguousarray(R), lam)
    if n == 0:
        return -Xs[:, :, 0], np.zeros(0)
    Ff, Xf = F.reshape(-1, n), Xs.reshape(-1, n + 1)
    Sc = Htt + lam * np.eye(n) - Ff.T @ Xf[:, 1:]
    dt = -np.linalg.solve(Sc, gt - Ff.T @ Xf[:, 0])
    dp = -(Xs[:, :, 0] + Xs[:, :, 1:] @ dt)
    return dp, dt


class ArrowFactor:
    """H^-1 for H = [[Hpp, F], [F^T, Htt]] with Hpp block tridiagonal (blocks ``D``, ``B``): the pose chain
    eliminated first, the parameters' dense Schur complement factored once. ``solve`` takes right-hand sides
    ordered as the effect graph's columns (3 per pose, then the parameters), in time linear in the poses."""

    def __init__(self, D, B, F, Htt):
        self.D, self.B = np.ascontiguousarray(D), np.ascontiguousarray(B)
        self.K, self.n = D.shape[0], F.shape[2]
        self.F = F.reshape(-1, self.n)
        self.X = _chain_solve(self.D, self.B, np.ascontiguousarray(F), 0.0).reshape(-1, self.n)   # Hpp^-1 F
        self.Sc = np.linalg.cholesky(Htt - self.F.T @ self.X) if self.n else None
        if not (np.all(np.isfinite(self.X)) and (self.Sc is None or np.all(np.isfinite(self.Sc)))):
            raise np.linalg.LinAlgError("the pose chain is singular")

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, float)
        m = b.shape[1]
        bp, bt = b[:3 * self.K], b[3 * self.K:]
        y = _chain_solve(self.D, self.B, np.ascontiguousarray(bp.reshape(self.K, 3, m)), 0.0).reshape(-1, m)
        if not self.n:
            return y
        z = np.linalg.solve(self.Sc, bt - self.F.T @ y)
        dt = np.linalg.solve(self.Sc.T, z)
        return np.concatenate([y - self.X @ dt, dt])
