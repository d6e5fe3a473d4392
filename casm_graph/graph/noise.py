"""Noise levels from residuals, corrected for the degrees of freedom the fit used up.

At a least-squares optimum each residual group g (motion forward, lateral, turn; reading;
bearing) has E|r_g|^2 = sigma_g^2 (n_g - tr(P_gg)) with P = A (A^T A)^-1 A^T the hat matrix of the
whitened linearised system. Pose variables soak up much of the motion residual, so the raw RMS
underestimates the motion noise badly; the traces come from Hutchinson probes on a sparse LU.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from casm_graph.graph import chain, robust


class _Permuted:
    """A factorisation of P^T H P answering ``solve`` for H itself."""

    def __init__(self, lu, order: np.ndarray):
        self.lu, self.order = lu, order

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b, dtype=float)
        x[self.order] = self.lu.solve(np.ascontiguousarray(b[self.order]))
        return x


def information_lu(A: sp.csr_matrix, order: np.ndarray | None = None):
    """Sparse LU of the information matrix A^T A of the whitened Jacobian ``A``.

    ``order``: a fill-reducing order of A's columns known to the caller (the poses in time order, then the
    parameters); SuperLU's minimum-degree ordering otherwise, which takes time quadratic in the number of
    poses on a long log.
    """
    H = (A.T @ A).tocsc()
    if order is not None:
        H = H[order][:, order].tocsc()
        try:
            return _Permuted(splu(H, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}),
                             order)
        except RuntimeError:
            return _Permuted(splu(H, permc_spec="MMD_AT_PLUS_A"), order)
    try:        # H is symmetric positive definite: no pivoting keeps the fill-reducing order (~20x less fill)
        return splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        return splu(H, permc_spec="MMD_AT_PLUS_A")


def information_solver(A: sp.csr_matrix, n_poses: int):
    """Something whose ``solve`` answers (A^T A)^-1 b for the whitened Jacobian ``A`` of a log's graph (poses
    first, then the parameters): the pose chain's block elimination (O(length) memory), the sparse LU in that
    order when the chain is singular, the chain with a tiny ridge (``chain.RIDGES``) when both are; None when
    nothing works. The one solver of every graph's noise step, table or command map."""
    solver = chain.arrow_solver(A, n_poses)
    if solver is not None:
        return solver
    try:
        return information_lu(A, np.arange(A.shape[1]))
    except RuntimeError:
        return chain.arrow_solver(A, n_poses, chain.RIDGES)


def leverages(A: sp.csr_matrix, rows: np.ndarray, lu=None) -> np.ndarray:
    """Exact diagonal of the hat matrix A (A^T A)^-1 A^T at ``rows`` of the whitened Jacobian ``A``
    (``lu``: :func:`information_lu` of ``A`` when the caller has it)."""
    lu = lu if lu is not None else information_lu(A)
    U = A[rows].T.toarray()
    return np.einsum("ij,ij->j", U, lu.solve(U))


def hat_traces(A: sp.csr_matrix, groups: dict[str, np.ndarray], probes: int = 24,
               seed: int = 0, lu=None, order: np.ndarray | None = None) -> dict[str, float]:
    """tr(P_gg) for each row group of the whitened Jacobian ``A``, by Hutchinson's estimator
    (``order``: as for :func:`information_lu`)."""
    lu = lu if lu is not None else information_lu(A, order)
    rng = np.random.default_rng(seed)
    out = {}
    for name, rows in groups.items():
        Z = rng.choice([-1.0, 1.0], size=(len(rows), probes))
        U = np.asarray(A[rows].T @ Z)
        out[name] = float(np.einsum("ij,ij->j", U, lu.solve(U)).mean())
    return out


def group_scales(e: np.ndarray, groups: dict[str, np.ndarray], traces: dict[str, float],
                 counts: dict[str, float] | None = None, huber: tuple[str, ...] = ()) -> dict[str, float]:
    """Factor by which each group's sigma should change, from its whitened residuals ``e`` at the optimum.

    Groups named in ``huber`` carry Huber-weighted residuals (:mod:`casm_graph.graph.robust`): their rows
    beyond the gate are set aside (with their share of the hat trace) and the sum of squares is
    divided by the Huber weighting's Gaussian efficiency, so a clean log gets the plain estimate and a
    wild sighting does not inflate it. ``counts`` overrides a group's row count (mixture weights).
    """
    out = {}
    for name, rows in groups.items():
        r = e[rows]
        if len(r) == 0:
            out[name] = 1.0          # a channel the log does not measure keeps its level (it is unknown)
            continue
        n, trace = (counts or {}).get(name, len(rows)), traces[name]
        rss = float(np.sum(r ** 2))
        if name in huber and len(r):
            keep = np.abs(r) <= np.sqrt(robust.HUBER * robust.GATE)      # |z| <= GATE, in Huber-weighted units
            trace *= keep.sum() / len(r)
            n = n * keep.sum() / len(r)
            rss = float(np.sum(r[keep] ** 2)) / robust.HUBER_EFFICIENCY
        out[name] = rescale(1.0, rss, max(int(round(n)), 1), trace)
    return out


def rescale(sigma: float, whitened_rss: float, n: int, trace: float) -> float:
    """New sigma from a group's whitened residual sum of squares under the old ``sigma``."""
    return float(sigma * np.sqrt(whitened_rss / max(n - trace, 1.0)))
