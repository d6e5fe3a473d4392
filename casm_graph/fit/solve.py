"""Levenberg-Marquardt driven from Python over a :class:`casm_graph.graph.table.Problem`, and the marginals.

GTSAM's stock optimizers call a ``CustomFactor`` back into Python per factor and copy the whole
``Values`` each time; here each iteration is one numpy pass to linearise, one GTSAM multifrontal
solve of the damped linear system, and one numpy pass to evaluate the trial. The final marginals
come from a selected inversion of the pose chain and its dense parameter block (:func:`chain_marginals`),
O(length) where ``gtsam.Marginals`` is slow and memory-hungry on a long chain.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.linalg import solve_triangular

from casm_graph.graph.table import Problem, State


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
        g.add(key, s * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim))
    return g


RIDGES = (1e-10, 1e-8, 1e-6)       # ridges tried, relative to the largest information, when a system is singular
PIVOT_TOL = 1e-12                   # a pivot below this share of its variable's own information counts as singular
CHUNK_DOUBLES = 4_000_000           # right-hand sides of the chain solves go through in blocks of about this size
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


@njit(cache=True)
def _chain_factor(D, B, ridge, tol):
    """Forward block elimination of the block-tridiagonal H (diagonal D + ridge I, upper blocks B).

    Returns the inverse pivots S_i^-1, G_i = B_{i-1}^T S_{i-1}^-1 (G_0 unused) and False when a pivot
    is not positive definite (below ``tol`` times its variable's own information).
    """
    K = D.shape[0]
    Sinv = np.empty_like(D)
    G = np.zeros_like(D)
    S = np.empty((3, 3))
    for i in range(K):
        for a in range(3):
            for b in range(3):
                S[a, b] = D[i, a, b]
            S[a, a] += ridge
        if i > 0:
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += B[i - 1, k, a] * Sinv[i - 1, k, b]
                    G[i, a, b] = acc
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += G[i, a, k] * B[i - 1, k, b]
                    S[a, b] -= acc
        # S = L diag(d) L^T with L unit lower; S^-1 = M^T diag(1/d) M with M = L^-1
        d0 = S[0, 0]
        if not d0 > tol * (D[i, 0, 0] + ridge):
            return Sinv, G, False
        l10, l20 = 0.5 * (S[1, 0] + S[0, 1]) / d0, 0.5 * (S[2, 0] + S[0, 2]) / d0
        d1 = S[1, 1] - l10 * l10 * d0
        if not d1 > tol * (D[i, 1, 1] + ridge):
            return Sinv, G, False
        l21 = (0.5 * (S[2, 1] + S[1, 2]) - l20 * l10 * d0) / d1
        d2 = S[2, 2] - l20 * l20 * d0 - l21 * l21 * d1
        if not d2 > tol * (D[i, 2, 2] + ridge):
            return Sinv, G, False
        m10, m20, m21 = -l10, l10 * l21 - l20, -l21
        i0, i1, i2 = 1.0 / d0, 1.0 / d1, 1.0 / d2
        Sinv[i, 0, 0] = i0 + m10 * m10 * i1 + m20 * m20 * i2
        Sinv[i, 1, 1] = i1 + m21 * m21 * i2
        Sinv[i, 2, 2] = i2
        Sinv[i, 0, 1] = Sinv[i, 1, 0] = m10 * i1 + m20 * m21 * i2
        Sinv[i, 0, 2] = Sinv[i, 2, 0] = m20 * i2
        Sinv[i, 1, 2] = Sinv[i, 2, 1] = m21 * i2
    return Sinv, G, True


@njit(cache=True)
def _chain_apply(Sinv, G, B, R):
    """H^-1 R in place for the factored block-tridiagonal H and right-hand sides R (K, 3, m)."""
    K, _, m = R.shape
    t = np.empty((3, m))
    for i in range(1, K):
        for a in range(3):
            for k in range(3):
                g = G[i, a, k]
                for c in range(m):
                    R[i, a, c] -= g * R[i - 1, k, c]
    for i in range(K - 1, -1, -1):
        for a in range(3):
            for c in range(m):
                t[a, c] = R[i, a, c]
        if i < K - 1:
            for a in range(3):
                for k in range(3):
                    b = B[i, a, k]
                    for c in range(m):
                        t[a, c] -= b * R[i + 1, k, c]
        for a in range(3):
            for c in range(m):
                R[i, a, c] = Sinv[i, a, 0] * t[0, c] + Sinv[i, a, 1] * t[1, c] + Sinv[i, a, 2] * t[2, c]


@njit(cache=True)
def _chain_cov(Sinv, B):
    """Diagonal blocks of the block-tridiagonal H's inverse (the Takahashi / RTS backward recursion)."""
    K = Sinv.shape[0]
    cov = np.empty_like(Sinv)
    cov[K - 1] = Sinv[K - 1]
    P = np.empty((3, 3))
    Q = np.empty((3, 3))
    for i in range(K - 2, -1, -1):
        for a in range(3):              # P = S_i^-1 B_i
            for b in range(3):
                P[a, b] = Sinv[i, a, 0] * B[i, 0, b] + Sinv[i, a, 1] * B[i, 1, b] + Sinv[i, a, 2] * B[i, 2, b]
        for a in range(3):              # Q = P cov_{i+1}
            for b in range(3):
                Q[a, b] = P[a, 0] * cov[i + 1, 0, b] + P[a, 1] * cov[i + 1, 1, b] + P[a, 2] * cov[i + 1, 2, b]
        for a in range(3):
            for b in range(a, 3):
                v = Sinv[i, a, b] + Q[a, 0] * P[b, 0] + Q[a, 1] * P[b, 1] + Q[a, 2] * P[b, 2]
                cov[i, a, b] = v
                cov[i, b, a] = v
    return cov


@njit(cache=True)
def _add_outer(cov, Z):
    """cov[i] += Z[i] Z[i]^T for every pose i."""
    K, _, m = Z.shape
    for i in range(K):
        for a in range(3):
            for b in range(a, 3):
                acc = 0.0
                for c in range(m):
                    acc += Z[i, a, c] * Z[i, b, c]
                cov[i, a, b] += acc
                if b != a:
                    cov[i, b, a] += acc


def arrow_blocks(A: sp.spmatrix, n_poses: int) -> dict:
    """Blocks of the information matrix H = A^T A of a Jacobian whose first 3 ``n_poses`` columns are a pose
    chain (each factor touching at most two consecutive poses) and the rest one dense parameter block."""
    H = (A.T @ A).tocsr()
    m, K = 3 * n_poses, n_poses
    Hpp = H[:m, :m].tocoo()
    rb, cb = Hpp.row // 3, Hpp.col // 3
    if np.any(np.abs(rb - cb) > 1):
        raise ValueError("not a pose chain: a factor joins poses more than one step apart")
    D, B = np.zeros((K, 3, 3)), np.zeros((max(K - 1, 0), 3, 3))
    on, up = rb == cb, cb == rb + 1
    D[rb[on], Hpp.row[on] % 3, Hpp.col[on] % 3] = Hpp.data[on]
    B[rb[up], Hpp.row[up] % 3, Hpp.col[up] % 3] = Hpp.data[up]
    F = H[:m, m:]
    return {"D": D, "B": B, "F": F.tocsr(), "Fc": F.tocsc(), "Htt": H[m:, m:].toarray(),
            "top": float(H.diagonal().max(initial=0.0))}


class ArrowSolve:
    """The block elimination of H + ridge I (H from :func:`arrow_blocks`): the pose chain once, then the
    Schur complement S = Htt - F^T Hpp^-1 F of the parameters (Cholesky). ``solve`` answers H^-1 b as a
    sparse LU of H would (the noise step's hat traces), in O(K) memory. Raises ``numpy.linalg.LinAlgError``
    when H + ridge I is not positive definite.
    """

    def __init__(self, blocks: dict, ridge: float = 0.0):
        self.B, self.F, Htt = blocks["B"], blocks["F"], blocks["Htt"]
        self.K, self.n = blocks["D"].shape[0], Htt.shape[0]
        self.c = max(1, CHUNK_DOUBLES // (3 * self.K))          # right-hand sides per chain sweep
        self.Sinv, self.G, ok = _chain_factor(blocks["D"], self.B, ridge, PIVOT_TOL)
        if not ok:
            raise np.linalg.LinAlgError("pose chain not positive definite")
        S = Htt + ridge * np.eye(self.n)
        Fc = blocks["Fc"]
        for j in range(0, self.n, self.c):
            S[:, j:j + self.c] -= self.F.T @ self.chain_solve(Fc[:, j:j + self.c].toarray())
        S = 0.5 * (S + S.T)
        self.L = np.linalg.cholesky(S) if self.n else np.zeros((0, 0))
        if not np.all(np.diag(self.L) ** 2 > PIVOT_TOL * (np.diag(Htt) + ridge)):
            raise np.linalg.LinAlgError("parameter block not positive definite")

    def chain_solve(self, R: np.ndarray) -> np.ndarray:
        """Hpp^-1 R for R (3K, m) over the pose columns only."""
        X = np.array(R, dtype=float, order="C").reshape(self.K, 3, -1)
        _chain_apply(self.Sinv, self.G, self.B, X)
        return X.reshape(3 * self.K, -1)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """H^-1 b for b (3K + n,) or (3K + n, m)."""
        b2 = np.asarray(b, float).reshape(len(b), -1)
        m = 3 * self.K
        out = np.empty_like(b2)
        for j in range(0, b2.shape[1], self.c):
            bp, bt = b2[:m, j:j + self.c], b2[m:, j:j + self.c]
            xt = bt - self.F.T @ self.chain_solve(bp)
            if self.n:
                xt = solve_triangular(self.L.T, solve_triangular(self.L, xt, lower=True), lower=False)
            out[:m, j:j + self.c] = self.chain_solve(bp - self.F @ xt)
            out[m:, j:j + self.c] = xt
        return out.reshape(np.shape(b))


def arrow_inverse(blocks: dict, ridge: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pose covariances (K, 3, 3) and the parameter block's covariance of H + ridge I, from :func:`arrow_blocks`.

    The chain is eliminated once (O(K)); the parameters' covariance is the inverse of their Schur
    complement S = L L^T, and each pose's adds Z_i Z_i^T (Z = Hpp^-1 F L^-T) to its covariance within the
    chain (the Takahashi recursion). Right-hand sides go through in column blocks, so memory stays O(K).
    Raises ``numpy.linalg.LinAlgError`` when H + ridge I is not positive definite.
    """
    a = ArrowSolve(blocks, ridge)
    cov = _chain_cov(a.Sinv, a.B)
    if a.n == 0:
        return cov, np.zeros((0, 0))
    M = solve_triangular(a.L, np.eye(a.n), lower=True).T          # S^-1 = M M^T
    for j in range(0, a.n, a.c):
        Z = a.chain_solve(np.asarray(a.F @ M[:, j:j + a.c])).reshape(a.K, 3, -1)
        _add_outer(cov, Z)
    return cov, M @ M.T


def arrow_solver(A: sp.spmatrix, n_poses: int) -> ArrowSolve | None:
    """:class:`ArrowSolve` of the whitened Jacobian ``A`` (poses first), or None when A^T A is singular or not
    a chain (the caller's sparse LU then answers)."""
    try:
        return ArrowSolve(arrow_blocks(A, n_poses))
    except (np.linalg.LinAlgError, ValueError):
        return None


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


def least_squares(problem: Problem, st: State, max_iterations: int = 30, rel_tol: float = 1e-6,
                  lam: float = 1e-6, on_iteration=None, freeze_parameters: bool = False) -> tuple[State, History]:
    """Minimise ``problem.cost`` from ``st``; returns the new state and the cost history.

    ``freeze_parameters`` holds the velocity table and polynomial where they are (poses only).
    A problem with ``normal_equations``/``solve_damped`` (the effect graph, whose parameters form one
    dense block) is solved by its own pose-chain elimination; otherwise GTSAM solves the linear graph.
    """
    hist = History()
    keys_dims = problem.keys_dims()
    if freeze_parameters:
        keys_dims = keys_dims[:problem.lay.n_poses]
    cost = problem.cost(st)
    hist.cost.append(cost)
    direct = hasattr(problem, "solve_damped")
    damping = {}                # lam moves by factors of ten: each level's damping graph is built once
    # the problem's own elimination order when it has one (GTSAM's default COLAMD costs time quadratic
    # in the number of poses on a long log); the same for every iteration, so computed once
    order = problem.ordering(freeze_parameters) if not direct and hasattr(problem, "ordering") else None
    for _ in range(max_iterations):
        if direct:
            neq = problem.normal_equations(st, poses_only=freeze_parameters)
        else:
            lin = problem.linearize(st, poses_only=freeze_parameters)
        while True:
            if direct:
                try:
                    trial = problem.retract(st, problem.solve_damped(neq, lam))
                except np.linalg.LinAlgError:   # singular at this damping (cancellation in the chain): damp more
                    trial = None
            else:
                if lam not in damping:
                    damping[lam] = _damping(keys_dims, lam)
                system = gtsam.GaussianFactorGraph()      # shares the factors of lin and the damping (no copy)
                system.push_back(lin)
                system.push_back(damping[lam])
                try:
                    trial = problem.retract(st, system.optimize() if order is None else system.optimize(order))
                except RuntimeError:        # GTSAM: indeterminate at this damping; damp more, as for a failed step
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
