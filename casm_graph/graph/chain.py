"""Pose chains: the Gauss-Newton information of a log's graph, eliminated along the chain in time linear in it.

Action factors link only consecutive poses and sightings touch one pose each, so the poses' information
is block tridiagonal (3x3 blocks); the model's parameters (table, polynomial, effects) add one dense
block coupled to every pose, an arrow. A forward block elimination and a backward pass (the
Rauch-Tung-Striebel / Takahashi recursion) give every pose's covariance and log det H in O(K)
(:func:`select_inverse`); with the parameters, :class:`ArrowSolve` eliminates the chain once and
factors the parameters' Schur complement, answering H^-1 b (the noise step's hat traces) and the
marginals (:func:`arrow_inverse`) as a sparse LU would, in O(K) memory. Coordinates are GTSAM's Pose2
tangent (body-frame dx, dy, dtheta), as in the factors.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.linalg import solve_triangular


RIDGES = (1e-10, 1e-8, 1e-6)        # ridges tried, relative to the largest information, when a system is singular
PIVOT_TOL = 1e-12                   # a pivot below this share of its variable's own information counts as singular
CHUNK_DOUBLES = 4_000_000           # right-hand sides of the chain solves go through in blocks of about this size


def information_blocks(problem, st, rows=None) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal (K, 3, 3) and upper off-diagonal (K-1, 3, 3) blocks of J^T J over the poses of ``problem``
    (a :class:`casm_graph.graph.problem.Problem`) at ``st`` (``rows``: its rows when the caller has them already)."""
    r = problem.rows(st, parameters=False) if rows is None else rows
    K = problem.lay.n_poses
    Ha, Hb, _ = r.action_J
    D = np.zeros((K, 3, 3))
    D[:-1] += np.einsum("nki,nkj->nij", Ha, Ha)
    D[1:] += np.einsum("nki,nkj->nij", Hb, Hb)
    B = np.einsum("nki,nkj->nij", Ha, Hb)
    knot, Jp, _, _ = problem.sighting_rows(r, parameters=False)
    np.add.at(D, knot, np.einsum("ni,nj->nij", Jp, Jp))
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


def factor_chain(D, B, ridge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_chain_factor` of the block-tridiagonal H + ridge I: (S^-1, G, B as contiguous) for
    :func:`_chain_apply`; ``numpy.linalg.LinAlgError`` when a pivot is not positive definite."""
    B = np.ascontiguousarray(B, dtype=float)
    Sinv, G, ok = _chain_factor(np.ascontiguousarray(D, dtype=float), B, float(ridge), PIVOT_TOL)
    if not ok:
        raise np.linalg.LinAlgError("the pose chain is not positive definite")
    return Sinv, G, B


def _chain_solve(D, B, R, lam):
    """H^-1 R for the block-tridiagonal H = blocks (D + lam I, B) and many right-hand sides R (K, 3, m), by
    :func:`factor_chain` and :func:`_chain_apply`."""
    Sinv, G, B = factor_chain(D, B, lam)
    X = np.array(R, dtype=float, order="C", copy=True)
    _chain_apply(Sinv, G, B, X)
    return X


@njit(cache=True)
def _coupling_product(F, X):
    """sum_i F[i]^T X[i] for F (K, 3, n) and X (K, 3, m), skipping F's zero columns: a pose couples to a few
    parameters (its action's velocities, the polynomial, the effects), a few percent of the dense block."""
    K, _, n = F.shape
    m = X.shape[2]
    out = np.zeros((n, m))
    for i in range(K):
        for c in range(n):
            f0, f1, f2 = F[i, 0, c], F[i, 1, c], F[i, 2, c]
            if f0 != 0.0 or f1 != 0.0 or f2 != 0.0:
                for j in range(m):
                    out[c, j] += f0 * X[i, 0, j] + f1 * X[i, 1, j] + f2 * X[i, 2, j]
    return out


@njit(cache=True)
def _parameter_blocks(Ha, Hb, Ht, ae, knot, Jp, Jt, eo):
    """The parameter parts of J^T J and J^T e: coupling F (K, 3, n), the parameters' block and gradient.

    Motion row blocks (3 rows per step, Jacobians ``Ha``, ``Hb`` on consecutive poses and ``Ht`` on the
    parameters) and sighting rows (``Jp`` on pose ``knot``, ``Jt``), each touching a few of the n parameters
    (its action's velocities, the polynomial, the effects): only those columns are visited."""
    S, _, n = Ht.shape
    F = np.zeros((S + 1, 3, n))
    Htt = np.zeros((n, n))
    gt = np.zeros(n)
    cols = np.empty(n, np.int64)
    for s in range(S):
        m = 0
        for c in range(n):
            if Ht[s, 0, c] != 0.0 or Ht[s, 1, c] != 0.0 or Ht[s, 2, c] != 0.0:
                cols[m] = c
                m += 1
        for u in range(m):
            c = cols[u]
            for i in range(3):
                F[s, i, c] += Ha[s, 0, i] * Ht[s, 0, c] + Ha[s, 1, i] * Ht[s, 1, c] + Ha[s, 2, i] * Ht[s, 2, c]
                F[s + 1, i, c] += Hb[s, 0, i] * Ht[s, 0, c] + Hb[s, 1, i] * Ht[s, 1, c] + Hb[s, 2, i] * Ht[s, 2, c]
            gt[c] += Ht[s, 0, c] * ae[s, 0] + Ht[s, 1, c] * ae[s, 1] + Ht[s, 2, c] * ae[s, 2]
            for v in range(m):
                d = cols[v]
                Htt[c, d] += Ht[s, 0, c] * Ht[s, 0, d] + Ht[s, 1, c] * Ht[s, 1, d] + Ht[s, 2, c] * Ht[s, 2, d]
    for r in range(Jt.shape[0]):
        m = 0
        for c in range(n):
            if Jt[r, c] != 0.0:
                cols[m] = c
                m += 1
        k = knot[r]
        for u in range(m):
            c = cols[u]
            jc = Jt[r, c]
            for i in range(3):
                F[k, i, c] += Jp[r, i] * jc
            gt[c] += jc * eo[r]
            for v in range(m):
                Htt[c, cols[v]] += jc * Jt[r, cols[v]]
    return F, Htt, gt


def normal_equations(Ha, Hb, Ht, ae, knot, Jp, Jt, eo, prior, pe, poses_only: bool = False) -> tuple:
    """Blocks (D, B, F, gp, Htt, gt) of J^T J and J^T e for :func:`solve_arrow` from whitened rows: motion rows
    ``ae`` (S, 3) with Jacobians ``Ha``, ``Hb`` on consecutive poses and ``Ht`` on the parameters, sighting rows
    ``eo`` on pose ``knot`` with ``Jp`` and ``Jt``, and a diagonal prior ``prior`` with residual ``pe``."""
    K = len(Ha) + 1
    D = np.zeros((K, 3, 3))
    D[:-1] += np.einsum("nki,nkj->nij", Ha, Ha)
    D[1:] += np.einsum("nki,nkj->nij", Hb, Hb)
    B = np.einsum("nki,nkj->nij", Ha, Hb)
    gp = np.zeros((K, 3))
    gp[:-1] += np.einsum("nki,nk->ni", Ha, ae)
    gp[1:] += np.einsum("nki,nk->ni", Hb, ae)
    at = sp.csr_matrix((np.ones(len(knot)), (knot, np.arange(len(knot)))), shape=(K, len(knot)))
    D += (at @ np.einsum("ni,nj->nij", Jp, Jp).reshape(len(knot), 9)).reshape(K, 3, 3)   # per pose: sums over
    gp += at @ (Jp * eo[:, None])                                                        # its sightings
    if poses_only:
        return D, B, np.zeros((K, 3, 0)), gp, np.zeros((0, 0)), np.zeros(0)
    F, Htt, gt = _parameter_blocks(*(np.ascontiguousarray(a, dtype=float) for a in (Ha, Hb, Ht, ae)),
                                   np.ascontiguousarray(knot, dtype=np.int64),
                                   *(np.ascontiguousarray(a, dtype=float) for a in (Jp, Jt, eo)))
    return D, B, F, gp, Htt + np.diag(prior ** 2), gt + prior * pe


def solve_arrow(D, B, F, gp, Htt, gt, lam):
    """Solve [[Hpp + lam I, F], [F^T, Htt + lam I]] [dp; dt] = -[gp; gt] with Hpp block tridiagonal.

    ``D`` (K,3,3) and ``B`` (K-1,3,3) are Hpp's blocks, ``F`` (K,3,n) the pose-parameter coupling.
    Eliminates the pose chain first (as GTSAM does with the parameters ordered last), then solves
    the dense Schur complement on the parameters.
    """
    n = F.shape[2]
    Sinv, G, B = factor_chain(D, B, lam)
    Xs = np.empty((len(D), 3, n + 1))
    Xs[:, :, 0], Xs[:, :, 1:] = gp, F
    _chain_apply(Sinv, G, B, Xs)                                    # Hpp^-1 [gp, F]
    if n == 0:
        return -Xs[:, :, 0], np.zeros(0)
    FX = _coupling_product(np.ascontiguousarray(F), Xs)          # F^T Hpp^-1 [gp, F]
    Sc = Htt + lam * np.eye(n) - 0.5 * (FX[:, 1:] + FX[:, 1:].T)
    dt = -np.linalg.solve(Sc, gt - FX[:, 0])
    dp = -(Xs[:, :, 0] + Xs[:, :, 1:] @ dt)
    return dp, dt



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
        self.Sinv, self.G, self.B = factor_chain(blocks["D"], self.B, ridge)
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


def arrow_solver(A: sp.spmatrix, n_poses: int, ridges=(0.0,)) -> ArrowSolve | None:
    """:class:`ArrowSolve` of the whitened Jacobian ``A`` (poses first) at the first of ``ridges`` (relative to
    the largest information) that works, or None when A^T A stays singular or is not a chain."""
    try:
        blocks = arrow_blocks(A, n_poses)
    except ValueError:
        return None
    for rel in ridges:
        try:
            return ArrowSolve(blocks, rel * blocks["top"])
        except np.linalg.LinAlgError:
            continue
    return None
