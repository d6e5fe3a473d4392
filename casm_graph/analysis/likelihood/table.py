"""log p(O | lambda) of an action-table log: poses, velocity table, sensor polynomial and the effects'
least-squares parameters integrated out (:class:`MarginalLikelihood`).

Re-factoring H for every lambda is the cost. Poses form a chain and each table row touches the
poses of its own segments only, so the kernel eliminates each action segment's interior poses
into its two boundary poses and its few parameters (nested dissection in time), then the short
chain of boundary poses into the dense parameter block: O(T) small dense work, no fill across
segments. Mixture rows (``false_detections``) enter with their exact log density at the MAP
residuals and the inlier responsibility as Gauss-Newton weight.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from casm_graph.analysis.likelihood.base import (LOG2PI, MOTION_NAMES, NoiseLikelihood, NoiseParameter,
                                                 length_factors)
from casm_graph.fit.outliers import kept
from casm_graph.fit.solve import least_squares
from casm_graph.graph import table as G
from casm_graph.graph.augmented import instantiate, theta_from_model
from casm_graph.graph.problem import Problem, State
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects import of_model
from casm_graph.models.model import Model


# ----------------------------------------------------------------------------------- kernels
@njit(cache=True)
def _add_row(M, g, idx, j, nnz, e, w):
    """M += w j j', g += w j e over the ``nnz`` nonzero entries ``j`` at positions ``idx``."""
    for a in range(nnz):
        ja = w * j[a]
        ia = idx[a]
        g[ia] += ja * e
        for b in range(nnz):
            M[ia, idx[b]] += ja * j[b]


@njit(cache=True)
def _eliminate(M, g, s, W):
    """Schur-eliminate the 3 variables at ``s`` from (M, g) in place; returns (log det of their block, g' C^-1 g)."""
    a00, a01, a02 = M[s, s], M[s, s + 1], M[s, s + 2]
    a10, a11, a12 = M[s + 1, s], M[s + 1, s + 1], M[s + 1, s + 2]
    a20, a21, a22 = M[s + 2, s], M[s + 2, s + 1], M[s + 2, s + 2]
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv = 1.0 / det
    Ci = np.empty((3, 3))
    Ci[0, 0] = c00 * inv
    Ci[1, 0] = c01 * inv
    Ci[2, 0] = c02 * inv
    Ci[0, 1] = (a02 * a21 - a01 * a22) * inv
    Ci[1, 1] = (a00 * a22 - a02 * a20) * inv
    Ci[2, 1] = (a01 * a20 - a00 * a21) * inv
    Ci[0, 2] = (a01 * a12 - a02 * a11) * inv
    Ci[1, 2] = (a02 * a10 - a00 * a12) * inv
    Ci[2, 2] = (a00 * a11 - a01 * a10) * inv
    n = M.shape[0]
    g0, g1, g2 = g[s], g[s + 1], g[s + 2]
    wg0 = Ci[0, 0] * g0 + Ci[0, 1] * g1 + Ci[0, 2] * g2
    wg1 = Ci[1, 0] * g0 + Ci[1, 1] * g1 + Ci[1, 2] * g2
    wg2 = Ci[2, 0] * g0 + Ci[2, 1] * g1 + Ci[2, 2] * g2
    for b in range(n):
        m0, m1, m2 = M[s, b], M[s + 1, b], M[s + 2, b]
        W[0, b] = Ci[0, 0] * m0 + Ci[0, 1] * m1 + Ci[0, 2] * m2
        W[1, b] = Ci[1, 0] * m0 + Ci[1, 1] * m1 + Ci[1, 2] * m2
        W[2, b] = Ci[2, 0] * m0 + Ci[2, 1] * m1 + Ci[2, 2] * m2
    for a in range(n):
        if a >= s and a < s + 3:
            continue
        m0, m1, m2 = M[a, s], M[a, s + 1], M[a, s + 2]
        if m0 == 0.0 and m1 == 0.0 and m2 == 0.0:
            continue
        g[a] -= m0 * wg0 + m1 * wg1 + m2 * wg2
        for b in range(a, n):
            if b >= s and b < s + 3:
                continue
            v = M[a, b] - (m0 * W[0, b] + m1 * W[1, b] + m2 * W[2, b])
            M[a, b] = v
            M[b, a] = v
    for a in range(n):
        for i in range(3):
            M[a, s + i] = 0.0
            M[s + i, a] = 0.0
    q = g0 * wg0 + g1 * wg1 + g2 * wg2
    g[s] = 0.0
    g[s + 1] = 0.0
    g[s + 2] = 0.0
    return np.log(det), q


@njit(cache=True)
def _motion_rows(M, g, sa, sb, Ha, Hb, Hl, e, wm, idx, j):
    L = Hl.shape[1]
    for c in range(3):
        nnz = 0
        for i in range(3):
            if Ha[c, i] != 0.0:
                idx[nnz] = sa + i
                j[nnz] = Ha[c, i]
                nnz += 1
            if Hb[c, i] != 0.0:
                idx[nnz] = sb + i
                j[nnz] = Hb[c, i]
                nnz += 1
        for i in range(L):
            if Hl[c, i] != 0.0:
                idx[nnz] = 9 + i
                j[nnz] = Hl[c, i]
                nnz += 1
        _add_row(M, g, idx, j, nnz, e[c], wm[c])


@njit(cache=True)
def _obs_rows(M, g, slot, Jp, Jl, eo, wo, lo, hi, idx, j):
    L = Jl.shape[1]
    for r in range(lo, hi):
        if wo[r] == 0.0:
            continue
        nnz = 0
        for i in range(3):
            if Jp[r, i] != 0.0:
                idx[nnz] = slot + i
                j[nnz] = Jp[r, i]
                nnz += 1
        for i in range(L):
            if Jl[r, i] != 0.0:
                idx[nnz] = 9 + i
                j[nnz] = Jl[r, i]
                nnz += 1
        _add_row(M, g, idx, j, nnz, eo[r], wo[r])


@njit(cache=True)
def reduce_segments(seg_k0, seg_k1, seg_cols, Ha, Hb, Hl, em, wm, obs_ptr, Jp, Jl, eo, wo, n_theta):
    """Eliminate every pose but the segment boundaries, then the boundary chain.

    Returns (log det of the eliminated pose blocks, their share of g' H^-1 g, the parameters'
    Schur complement S (n_theta, n_theta) and reduced gradient). Motion rows are weighted by
    ``wm`` per axis, observation rows by ``wo``; ``seg_cols`` maps each segment's local
    parameter columns to global ones (-1: padding). Active variables of a segment: its first
    pose (slot 0), the current and next pose (slots 3 and 6, alternating), local parameters (9:).
    """
    nseg = seg_k0.shape[0]
    L = seg_cols.shape[1]
    n = 9 + L
    nb = nseg + 1
    Db = np.zeros((nb, 3, 3))
    Bb = np.zeros((nseg, 3, 3))
    Fb = np.zeros((nb, 3, n_theta + 1))        # last column: the gradient
    Htt = np.zeros((n_theta + 1, n_theta + 1))
    logdet = 0.0
    gHg = 0.0
    M = np.zeros((n, n))
    g = np.zeros(n)
    W = np.zeros((3, n))
    idx = np.zeros(n, np.int64)
    j = np.zeros(n)
    for s in range(nseg):
        k0, k1 = seg_k0[s], seg_k1[s]
        M[:, :] = 0.0
        g[:] = 0.0
        if s == 0:
            _obs_rows(M, g, 0, Jp, Jl, eo, wo, obs_ptr[k0], obs_ptr[k0 + 1], idx, j)
        cur, nxt = 3, 6
        for k in range(k0, k1):
            sa = 0 if k == k0 else cur
            _motion_rows(M, g, sa, nxt, Ha[k], Hb[k], Hl[k], em[k], wm, idx, j)
            p = k + 1
            _obs_rows(M, g, nxt, Jp, Jl, eo, wo, obs_ptr[p], obs_ptr[p + 1], idx, j)
            if k > k0:
                ld, q = _eliminate(M, g, cur, W)
                logdet += ld
                gHg += q
            cur, nxt = nxt, cur
        last = cur                                # the slot holding pose k1
        for i in range(3):
            Fb[s, i, n_theta] += g[i]
            Fb[s + 1, i, n_theta] += g[last + i]
            for jj in range(3):
                Db[s, i, jj] += M[i, jj]
                Db[s + 1, i, jj] += M[last + i, last + jj]
                Bb[s, i, jj] += M[i, last + jj]
            for c in range(L):
                col = seg_cols[s, c]
                if col < 0:
                    continue
                Fb[s, i, col] += M[i, 9 + c]
                Fb[s + 1, i, col] += M[last + i, 9 + c]
        for a in range(L):
            ca = seg_cols[s, a]
            if ca < 0:
                continue
            Htt[ca, n_theta] += g[9 + a]
            for b in range(L):
                cb = seg_cols[s, b]
                if cb < 0:
                    continue
                Htt[ca, cb] += M[9 + a, 9 + b]
    # the boundary chain, eliminated into the parameters (the gradient rides along as column n_theta)
    Sinv = np.zeros((3, 3))
    Y = np.zeros((3, n_theta + 1))
    for i in range(nb):
        S = Db[i].copy()
        Yi = Fb[i].copy()
        if i > 0:
            G = Bb[i - 1].T @ Sinv
            S -= G @ Bb[i - 1]
            Yi -= G @ Y
        Sinv = np.linalg.inv(S)
        logdet += np.log(np.linalg.det(S))
        Htt -= Yi.T @ (Sinv @ Yi)
        Y = Yi
    gHg -= Htt[n_theta, n_theta]
    return logdet, gHg, Htt[:n_theta, :n_theta].copy(), Htt[:n_theta, n_theta].copy()


@njit(cache=True)
def chain_terms(Ha, Hb, em, wm, obs_ptr, Jp, eo, wo):
    """(log det H, g' H^-1 g) of the pose chain alone (parameters held fixed), one forward elimination."""
    K = obs_ptr.shape[0] - 1
    logdet = 0.0
    gHg = 0.0
    D = np.zeros((3, 3))
    B = np.zeros((3, 3))
    Bp = np.zeros((3, 3))
    Si = np.zeros((3, 3))
    T = np.zeros((3, 3))
    gk = np.zeros(3)
    cp = np.zeros(3)
    c = np.zeros(3)
    for k in range(K):
        D[:, :] = 0.0
        B[:, :] = 0.0
        gk[:] = 0.0
        if k > 0:
            for a in range(3):
                w = wm[a]
                for i in range(3):
                    hi = w * Hb[k - 1, a, i]
                    gk[i] += hi * em[k - 1, a]
                    for j in range(3):
                        D[i, j] += hi * Hb[k - 1, a, j]
        if k < K - 1:
            for a in range(3):
                w = wm[a]
                for i in range(3):
                    hi = w * Ha[k, a, i]
                    gk[i] += hi * em[k, a]
                    for j in range(3):
                        D[i, j] += hi * Ha[k, a, j]
                        B[i, j] += hi * Hb[k, a, j]
        for r in range(obs_ptr[k], obs_ptr[k + 1]):
            w = wo[r]
            for i in range(3):
                hi = w * Jp[r, i]
                gk[i] += hi * eo[r]
                for j in range(3):
                    D[i, j] += hi * Jp[r, j]
        if k > 0:
            # D -= Bp' Si Bp ; g -= Bp' Si cp
            for i in range(3):
                for j in range(3):
                    T[i, j] = Si[i, 0] * Bp[0, j] + Si[i, 1] * Bp[1, j] + Si[i, 2] * Bp[2, j]
            for i in range(3):
                for j in range(3):
                    D[i, j] -= Bp[0, i] * T[0, j] + Bp[1, i] * T[1, j] + Bp[2, i] * T[2, j]
                v = Si[i, 0] * cp[0] + Si[i, 1] * cp[1] + Si[i, 2] * cp[2]
                c[i] = v
            for i in range(3):
                gk[i] -= Bp[0, i] * c[0] + Bp[1, i] * c[1] + Bp[2, i] * c[2]
        # inverse and determinant of the 3x3 pivot
        a00, a01, a02 = D[0, 0], D[0, 1], D[0, 2]
        a10, a11, a12 = D[1, 0], D[1, 1], D[1, 2]
        a20, a21, a22 = D[2, 0], D[2, 1], D[2, 2]
        c00 = a11 * a22 - a12 * a21
        c01 = a12 * a20 - a10 * a22
        c02 = a10 * a21 - a11 * a20
        det = a00 * c00 + a01 * c01 + a02 * c02
        if not det > 0.0:
            return np.nan, np.nan
        inv = 1.0 / det
        Si[0, 0] = c00 * inv
        Si[1, 0] = c01 * inv
        Si[2, 0] = c02 * inv
        Si[0, 1] = (a02 * a21 - a01 * a22) * inv
        Si[1, 1] = (a00 * a22 - a02 * a20) * inv
        Si[2, 1] = (a01 * a20 - a00 * a21) * inv
        Si[0, 2] = (a01 * a12 - a02 * a11) * inv
        Si[1, 2] = (a02 * a10 - a00 * a12) * inv
        Si[2, 2] = (a00 * a11 - a01 * a10) * inv
        logdet += np.log(det)
        for i in range(3):
            cp[i] = gk[i]
            gHg += gk[i] * (Si[i, 0] * gk[0] + Si[i, 1] * gk[1] + Si[i, 2] * gk[2])
            for j in range(3):
                Bp[i, j] = B[i, j]
    return logdet, gHg


def noise_parameters(problem: Problem, model: Model, theta: np.ndarray) -> list[NoiseParameter]:
    """Every noise level of ``model``: sigmas, motion noise per axis, noise-only effect parameters."""
    out = [NoiseParameter(f"{ch}_sigma", ch, 0, float(getattr(model, f"{ch}_sigma")))
           for ch in ("reading", "bearing") if len(getattr(problem, f"{ch[0]}_knot")) and model.has(ch)]
    for c, name in enumerate(MOTION_NAMES):
        out.append(NoiseParameter(name, "motion", c, float(model.motion_noise[c])))
    for e, s in zip(problem.effects, problem.slices):
        if e.noise_only:
            for j, p in enumerate(e.params):
                upper = 0.5 if e.name == "false_detections" else np.inf
                out.append(NoiseParameter(f"{e.name}.{p}", "effect", s.start + j, float(theta[s][j]), 0.0, upper))
    return out


class MarginalLikelihood(NoiseLikelihood):
    """log p(O | lambda) by the fixed-linearisation Laplace approximation of the module docstring.

    Built once from a problem at its MAP state; each call re-weights the rows and re-factors the
    information matrix with :func:`reduce_segments` (about 1.2 us per step). With
    ``integrate_parameters=False`` the table, polynomial and effect parameters stay at the MAP
    and only the pose chain is integrated (:func:`chain_terms`, about 0.35 us per step): what
    the EKF's p(O | lambda) does, for the cross-check.
    """

    integrated_out = ("poses", "velocity table", "sensor polynomial", "effect parameters (least squares)")

    def set_aside(self) -> int:
        return self._set_aside

    def __init__(self, problem: Problem, st: State, model: Model, integrate_parameters: bool = True):
        self.problem, self.state, self.model = problem, st, model
        self.integrate = integrate_parameters
        measured = np.isfinite(problem.log.obs_reading) | np.isfinite(problem.log.obs_bearing)
        self._set_aside = int(np.sum(measured & ~problem.obs_mask))
        self.params = noise_parameters(problem, model, st.theta)
        self.names = [p.name for p in self.params]
        self.x_map = np.array([p.value for p in self.params])
        self._linearise()

    def _linearise(self) -> None:
        pb, st = self.problem, self.state
        # unit noise levels: rows() then returns raw sighting rows, and motion rows whitened by each segment's
        # length factor only (a step twice the median's is trusted half as much, as the calibration has it)
        keep = (pb.motion_sigma, pb.reading_sigma, pb.bearing_sigma, pb.r_scale, pb.weight)
        pb.motion_sigma, self.const = length_factors(pb, self.model)
        pb.reading_sigma = pb.bearing_sigma = 1.0
        pb.r_scale, pb.weight = np.ones_like(pb.r_scale), np.ones_like(pb.weight)
        try:
            r = pb.rows(st)
        finally:
            pb.motion_sigma, pb.reading_sigma, pb.bearing_sigma, pb.r_scale, pb.weight = keep
        K = pb.lay.n_poses
        Ha, Hb, Ht = r.action_J
        n_theta = pb.n_theta if self.integrate else 0
        self.n_theta = n_theta
        self.em = np.ascontiguousarray(r.action_e)
        self.motion_ss = np.sum(self.em ** 2, axis=0)
        self.n_steps = K - 1
        # observation rows (reading then bearing), sorted by pose
        knot = np.concatenate([pb.r_knot, pb.b_knot])
        Jp = np.concatenate([r.reading_J[0], r.bearing_J])
        Jt = np.concatenate([r.reading_J[1], r.bearing_Jt]) if n_theta else np.zeros((len(knot), 0))
        eo = np.concatenate([r.reading_e, r.bearing_e])
        row_kind = np.concatenate([np.zeros(len(pb.r_knot), int), np.ones(len(pb.b_knot), int)])
        row_obs = np.concatenate([pb.r_idx, pb.b_idx])
        order = np.argsort(knot, kind="stable")
        knot, Jp, Jt, eo = knot[order], Jp[order], Jt[order], eo[order]
        self.row_kind, self.row_obs = row_kind[order], row_obs[order]
        self.obs_ptr = np.searchsorted(knot, np.arange(K + 1)).astype(np.int64)
        # segments: runs of one action; local parameter columns = union of the nonzero columns
        cuts = np.flatnonzero(np.diff(pb.lay.seg_action) != 0) + 1
        k0 = np.concatenate([[0], cuts]).astype(np.int64)
        k1 = np.concatenate([cuts, [K - 1]]).astype(np.int64)
        cols = []
        for s, (a, b) in enumerate(zip(k0, k1)):
            nz = np.zeros(n_theta, bool)
            if n_theta:
                nz |= np.any(Ht[a:b] != 0, axis=(0, 1))
                nz |= np.any(Jt[self.obs_ptr[a + (s > 0)]:self.obs_ptr[b + 1]] != 0, axis=0)
            cols.append(np.flatnonzero(nz))
        L = max((len(c) for c in cols), default=0)
        seg_cols = np.full((len(k0), L), -1, np.int64)
        Hl = np.zeros((K - 1, 3, L))
        Jl = np.zeros((len(knot), L))
        for s, (a, b, c) in enumerate(zip(k0, k1, cols)):
            seg_cols[s, :len(c)] = c
            if len(c):
                Hl[a:b, :, :len(c)] = Ht[a:b][:, :, c]
                lo, hi = self.obs_ptr[a + (s > 0)], self.obs_ptr[b + 1]
                Jl[lo:hi, :len(c)] = Jt[lo:hi][:, c]
        self.seg_k0, self.seg_k1, self.seg_cols = k0, k1, seg_cols
        self.Ha, self.Hb, self.Hl = (np.ascontiguousarray(x) for x in (Ha, Hb, Hl))
        self.Jp, self.Jl, self.eo = np.ascontiguousarray(Jp), np.ascontiguousarray(Jl), eo
        self.prior_info = r.prior_J ** 2 if n_theta else np.zeros(0)
        self.prior_g = r.prior_J * r.prior_e if n_theta else np.zeros(0)
        # raw residuals (measured - predicted) and distances at the MAP, per observation
        pr = pb.predictions(st)
        self.res_r = pb.log.obs_reading - pr["reading"]
        self.res_b = wrap(pb.log.obs_bearing - pr["bearing"])
        self.distance = pr["distance"]
        self.mask = pb.obs_mask

    # ---------------------------------------------------------------------------- pieces
    def _split(self, x):
        """(reading sigma, bearing sigma, motion sigma (3,), effect theta) from a vector of noise levels."""
        th = self.state.theta.copy()
        mot = np.array(self.model.motion_noise, float)
        sr, sb = self.model.reading_sigma, self.model.bearing_sigma
        for p, v in zip(self.params, x):
            if p.kind == "reading":
                sr = v
            elif p.kind == "bearing":
                sb = v
            elif p.kind == "motion":
                mot[p.index] = v
            else:
                th[p.index] = v
        return float(sr), float(sb), mot, th

    def observation_terms(self, sr: float, sb: float, theta: np.ndarray):
        """Sum of the observations' log densities at the MAP residuals, and each row's Gauss-Newton weight."""
        scale = np.ones_like(self.distance)
        eps = 0.0
        for e, s in self.problem.sensor_effects:
            scale = scale * e.reading_scale(theta[s], self.distance, {})
            eps += e.outlier_fraction(theta[s])
        s_r = sr * scale
        ok_r = np.isfinite(self.res_r) & self.mask
        ok_b = np.isfinite(self.res_b) & self.mask
        lr = np.where(ok_r, -0.5 * (self.res_r / s_r) ** 2 - np.log(s_r) - 0.5 * LOG2PI, 0.0)
        lb = np.where(ok_b, -0.5 * (self.res_b / sb) ** 2 - np.log(sb) - 0.5 * LOG2PI, 0.0)
        lin = lr + lb
        if eps > 0:
            lout = (np.where(ok_r, -np.log(self.problem.reading_span), 0.0)
                    + np.where(ok_b, -np.log(2 * np.pi), 0.0))
            lmix = np.logaddexp(np.log1p(-eps) + lin, np.log(eps) + lout)
            resp = np.exp(np.log1p(-eps) + lin - lmix)
        else:
            lmix, resp = lin, np.ones_like(lin)
        w_obs = resp[self.row_obs]
        w = np.where(self.row_kind == 0, w_obs / s_r[self.row_obs] ** 2, w_obs / sb ** 2)
        w = np.where(self.mask[self.row_obs], w, 0.0)
        return float(np.sum(lmix[self.mask])), w

    def _weights(self, x):
        sr, sb, mot, th = self._split(np.asarray(x, float))
        lobs, wo = self.observation_terms(sr, sb, th)
        wm = 1.0 / mot ** 2
        lmot = float(-0.5 * np.sum(self.motion_ss * wm) - self.n_steps * np.sum(np.log(mot))
                     - 1.5 * self.n_steps * LOG2PI + self.const)
        return lmot + lobs, wm, wo

    def reduce(self, x):
        """(data log density, log det, g' H^-1 g of the poses, parameter Schur complement S, reduced gradient)."""
        ldata, wm, wo = self._weights(x)
        logdet, gHg, S, gt = reduce_segments(self.seg_k0, self.seg_k1, self.seg_cols, self.Ha, self.Hb, self.Hl,
                                             self.em, wm, self.obs_ptr, self.Jp, self.Jl, self.eo, wo,
                                             self.n_theta)
        if self.n_theta:
            S = S + np.diag(self.prior_info)
            gt = gt + self.prior_g
        return ldata, logdet, gHg, S, gt

    def terms(self, x) -> tuple[float, float, float]:
        """(data log density at the MAP residuals, log det H, g' H^-1 g) of the exact Laplace value."""
        ldata, logdet, gHg, S, gt = self.reduce(np.asarray(x, float))
        if self.n_theta:
            Lc = np.linalg.cholesky(S)
            logdet += 2 * np.sum(np.log(np.diag(Lc)))
            z = np.linalg.solve(Lc, gt)
            gHg += float(z @ z)
        return ldata, logdet, gHg

    def exact(self, x) -> float:
        """The Laplace value with poses, table, polynomial and effect parameters integrated out."""
        if not self.in_support(x):
            return -np.inf
        try:
            ldata, logdet, gHg = self.terms(x)
        except np.linalg.LinAlgError:
            return -np.inf
        return float(ldata + 0.5 * gHg - 0.5 * logdet)

    def poses_only(self, x) -> float:
        """The Laplace value with the table, polynomial and effect parameters held at the MAP."""
        if not self.in_support(x):
            return -np.inf
        ldata, wm, wo = self._weights(x)
        logdet, gHg = chain_terms(self.Ha, self.Hb, self.em, wm, self.obs_ptr, self.Jp, self.eo, wo)
        if not np.isfinite(logdet):
            return -np.inf
        return float(ldata + 0.5 * gHg - 0.5 * logdet)

    def __call__(self, x) -> float:
        """log p(O | x), up to a constant: the exact Laplace value (poses and parameters integrated); -inf where
        the noise levels are so extreme that a pose block is singular or a term overflows (a sampler's wild step)."""
        try:
            return self.exact(x) if self.n_theta else self.poses_only(x)
        except (ZeroDivisionError, OverflowError):
            return -np.inf

    def parameter_covariance(self, x) -> np.ndarray:
        """Laplace covariance (n_theta, n_theta) of table, polynomial and effect parameters at noise levels ``x``."""
        if not self.n_theta:
            raise ValueError("the parameters are held fixed in this likelihood")
        _, _, _, S, _ = self.reduce(np.asarray(x, float))
        return np.linalg.inv(S)

    def parameter_shift(self, x) -> np.ndarray:
        """Gauss-Newton change of table, polynomial and effect parameters from the MAP when the noise is ``x``."""
        _, _, _, S, gt = self.reduce(np.asarray(x, float))
        return -np.linalg.solve(S, gt)

    def parameter_moments(self, x) -> tuple[np.ndarray, np.ndarray]:
        """(Gauss-Newton shift, Laplace covariance) of table, polynomial and effect parameters at ``x``."""
        _, _, _, S, gt = self.reduce(np.asarray(x, float))
        C = np.linalg.inv(S)
        return -C @ gt, C


def map_state(log: Log, model: Model, poses: np.ndarray, iterations: int = 10) -> tuple[Problem, State]:
    """The effect graph of ``model`` on ``log`` and its MAP (poses, table, polynomial) at the model's noise.

    Gross outliers at ``poses`` are set aside first (:func:`casm_graph.fit.outliers.kept`, as the calibration
    prunes them): the likelihood is Gaussian, so one reading thousands of sigmas off would otherwise set the
    reading sigma the sampler sees."""
    effects = instantiate(of_model(model.effects), log)
    theta = theta_from_model(effects, model)
    problem = Problem(log, model, effects, theta=theta, obs_mask=kept(log, model, poses, effects), huber=False,
                      anchor=G.heading_anchor(log, poses))
    st = problem.state(poses, model, theta)
    problem.refresh_noise_state(st)
    st, _ = least_squares(problem, st, max_iterations=iterations)
    problem.refresh_noise_state(st)
    return problem, st


def likelihood(log: Log, model: Model, poses: np.ndarray, integrate_parameters: bool = True,
               iterations: int = 10) -> MarginalLikelihood:
    """:class:`MarginalLikelihood` of ``model`` on ``log`` linearised at the MAP found from ``poses``."""
    problem, st = map_state(log, model, poses, iterations)
    return MarginalLikelihood(problem, st, model, integrate_parameters)
