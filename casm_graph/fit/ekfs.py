"""The EKFS E-step of the EKFS-EM paper, compiled: forward EKF, backward information filter, two-filter smoother.

Poses s_k = (x, y, theta) live at pose steps k = 0..T; step k runs an action with per-step body
displacement u_k = v dt and process noise R(theta) diag(sigma_A,k^2) R(theta)^T (``act_sig`` (T, 3), one row
per step: :func:`step_sigmas`). Frame k may carry
sightings o = (reading, bearing) of known landmarks, h(s) = (f(dist), angle - theta). The
backward filter starts with infinite covariance (zero information) and is linearised at the
forward filter's means. All per-step 3x3 algebra runs in numba.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


def step_sigmas(sigma, log) -> np.ndarray:
    """(T, 3) process-noise std of each step of ``log``: ``sigma`` per step of the median length, grown with the
    step's time as the graph's motion factors grow it (:meth:`casm_graph.io.log.Log.in_median_steps`)."""
    return np.asarray(sigma, float)[None, :] * np.sqrt(log.in_median_steps(log.dt))[:, None]


@njit(cache=True)
def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


@njit(cache=True)
def _inv3(A):
    return np.linalg.inv(A)


@njit(cache=True)
def _predict_jac(s, u):
    c, sn = math.cos(s[2]), math.sin(s[2])
    g = np.array([s[0] + c * u[0] - sn * u[1], s[1] + sn * u[0] + c * u[1], s[2] + u[2]])
    F = np.eye(3)
    F[0, 2] = -sn * u[0] - c * u[1]
    F[1, 2] = c * u[0] - sn * u[1]
    return g, F


@njit(cache=True)
def _process(theta, sig):
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ np.diag(sig ** 2) @ R.T


@njit(cache=True)
def _obs_rows(s, lm, poly, z_r, z_b):
    """Predicted (reading, bearing), Jacobian rows and innovations for one sighting."""
    dx, dy = lm[0] - s[0], lm[1] - s[1]
    r2 = dx * dx + dy * dy
    d = math.sqrt(r2)
    f = 0.0
    df = 0.0
    p = 1.0
    for i in range(poly.shape[0]):
        f += poly[i] * p
        if i + 1 < poly.shape[0]:
            df += (i + 1) * poly[i + 1] * p
        p *= d
    H = np.zeros((2, 3))
    H[0, 0], H[0, 1] = -df * dx / d, -df * dy / d
    H[1, 0], H[1, 1], H[1, 2] = dy / r2, -dx / r2, -1.0
    innov = np.array([z_r - f, _wrap(z_b - (math.atan2(dy, dx) - s[2]))])
    return H, innov


@njit(cache=True)
def forward(mu0, P0, u, act_sig, obs_ptr, obs_lm, obs_r, obs_b, poly, s_r, s_b, use):
    """EKF forward pass: filtered means/covariances at each pose (after its sightings), log p(O|lambda).

    ``obs_ptr[k]:obs_ptr[k+1]`` index the sightings of pose k; ``use`` masks them (outliers off);
    returns also each sighting's squared Mahalanobis innovation for outlier pruning.
    """
    K = u.shape[0] + 1
    mu = np.empty((K, 3))
    P = np.empty((K, 3, 3))
    m2 = np.full(obs_r.shape[0], np.nan)
    m = mu0.copy()
    C = P0.copy()
    loglik = 0.0
    for k in range(K):
        for j in range(obs_ptr[k], obs_ptr[k + 1]):
            H, innov = _obs_rows(m, obs_lm[j], poly, obs_r[j], obs_b[j])
            for row in range(2):
                z = obs_r[j] if row == 0 else obs_b[j]
                if math.isnan(z):
                    continue
                h = H[row]
                var = s_r ** 2 if row == 0 else s_b ** 2
                S = h @ C @ h + var
                if row == 0:
                    e = innov[0]
                else:
                    e = innov[1]
                m2j = e * e / S
                if row == 0:
                    m2[j] = m2j
                else:
                    m2[j] = m2j if math.isnan(m2[j]) else m2[j] + m2j
                if not use[j]:
                    continue
                loglik += -0.5 * (m2j + math.log(2 * math.pi * S))
                Kg = C @ h / S
                m = m + Kg * e
                m[2] = _wrap(m[2])
                C = C - np.outer(Kg, h @ C)
                C = 0.5 * (C + C.T)
                if row == 0:
                    H, innov = _obs_rows(m, obs_lm[j], poly, obs_r[j], obs_b[j])
        mu[k] = m
        P[k] = C
        if k < K - 1:
            g, F = _predict_jac(m, u[k])
            m = g
            m[2] = _wrap(m[2])
            C = F @ C @ F.T + _process(mu[k, 2], act_sig[k])
    return mu, P, loglik, m2


@njit(cache=True)
def backward(ref, u, act_sig, obs_ptr, obs_lm, obs_r, obs_b, poly, s_r, s_b, use):
    """Backward information filter from zero information at T, linearised at ``ref`` (K, 3).

    Returns (Lb, eb): information of beta_k (future sightings only) and (Ld, ed): of delta_k =
    b(s_k, o_k) beta_k, both as information matrix and vector in absolute coordinates.
    """
    K = ref.shape[0]
    Lb = np.zeros((K, 3, 3))
    eb = np.zeros((K, 3))
    Ld = np.zeros((K, 3, 3))
    ed = np.zeros((K, 3))
    L = np.zeros((3, 3))
    eta = np.zeros(3)
    I3 = np.eye(3)
    for k in range(K - 1, -1, -1):
        if k < K - 1:
            g, F = _predict_jac(ref[k], u[k])
            Q = _process(ref[k, 2], act_sig[k])
            A = _inv3(I3 + L @ Q)
            M = A @ L
            M = 0.5 * (M + M.T)
            # mean of delta_{k+1} relative to g, with the angle kept near g's
            off = g - F @ ref[k]
            shift = np.zeros(3)
            shift[2] = g[2] - ref[k + 1, 2]  # ref[k+1] and g differ by a multiple of 2pi at most
            shift[2] = shift[2] - _wrap(shift[2])
            e2 = eta + L @ shift
            L = F.T @ M @ F
            eta = F.T @ (A @ e2 - M @ off)
        Lb[k] = L
        eb[k] = eta
        for j in range(obs_ptr[k], obs_ptr[k + 1]):
            if not use[j]:
                continue
            H, innov = _obs_rows(ref[k], obs_lm[j], poly, obs_r[j], obs_b[j])
            for row in range(2):
                z = obs_r[j] if row == 0 else obs_b[j]
                if math.isnan(z):
                    continue
                h = H[row]
                w = 1.0 / (s_r ** 2 if row == 0 else s_b ** 2)
                L = L + w * np.outer(h, h)
                eta = eta + w * h * (innov[row] + h @ ref[k])
        Ld[k] = L
        ed[k] = eta
    return Lb, eb, Ld, ed


@njit(cache=True)
def smooth(mu_a, P_a, Lb, eb):
    """Two-filter combination gamma = alpha * beta in information form (angles relative to alpha)."""
    K = mu_a.shape[0]
    mu = np.empty((K, 3))
    P = np.empty((K, 3, 3))
    for k in range(K):
        Ia = _inv3(P_a[k])
        ref = mu_a[k].copy()
        e = eb[k] - Lb[k] @ ref          # information of beta about the offset from alpha's mean
        C = _inv3(Ia + Lb[k])
        d = C @ e
        mu[k] = ref + d
        mu[k, 2] = _wrap(mu[k, 2])
        P[k] = 0.5 * (C + C.T)
    return mu, P


@njit(cache=True)
def _d_and_L(z):
    """d(s, s') = (R(-theta)(p' - p), theta' - theta) at z = (s, s') and its 3x6 Jacobian."""
    c, s = math.cos(z[2]), math.sin(z[2])
    dx, dy = z[3] - z[0], z[4] - z[1]
    d = np.array([c * dx + s * dy, -s * dx + c * dy, z[5] - z[2]])
    L = np.zeros((3, 6))
    L[0, 0], L[0, 1], L[0, 2] = -c, -s, -s * dx + c * dy
    L[1, 0], L[1, 1], L[1, 2] = s, -c, -c * dx - s * dy
    L[2, 2] = -1.0
    L[0, 3], L[0, 4] = c, s
    L[1, 3], L[1, 4] = -s, c
    L[2, 5] = 1.0
    return d, L


@njit(cache=True)
def _pair_cost(z, a, Ia, Ld, ed, u, w):
    """-log of alpha(s) delta(s') f_A(d(s, s')) up to a constant; delta in information form, f_A's precision ``w``."""
    c, s = math.cos(z[2]), math.sin(z[2])
    dx, dy = z[3] - z[0], z[4] - z[1]
    e0 = c * dx + s * dy - u[0]
    e1 = -s * dx + c * dy - u[1]
    e2 = _wrap(z[5] - z[2]) - u[2]
    q = w[0] * e0 * e0 + w[1] * e1 * e1 + w[2] * e2 * e2
    lin = 0.0
    for i in range(3):
        lin += z[3 + i] * ed[i]
        for j in range(3):
            q += (z[i] - a[i]) * Ia[i, j] * (z[j] - a[j]) + z[3 + i] * Ld[i, j] * z[3 + j]
    return 0.5 * q - lin


@njit(cache=True)
def _cholesky_solve(H, g):
    """H^-1 g for a small symmetric positive definite H (columns of ``g``), by Cholesky in plain loops: numba's
    LAPACK calls cost more than the arithmetic at 6 x 6."""
    n = H.shape[0]
    R = np.zeros((n, n))
    for j in range(n):
        s = H[j, j]
        for m in range(j):
            s -= R[j, m] * R[j, m]
        R[j, j] = math.sqrt(s) if s > 0.0 else math.nan     # not positive definite: the caller falls back
        for i in range(j + 1, n):
            s = H[i, j]
            for m in range(j):
                s -= R[i, m] * R[j, m]
            R[i, j] = s / R[j, j]
    x = g.copy()
    for c in range(x.shape[1]):
        for i in range(n):
            s = x[i, c]
            for m in range(i):
                s -= R[i, m] * x[m, c]
            x[i, c] = s / R[i, i]
        for i in range(n - 1, -1, -1):
            s = x[i, c]
            for m in range(i + 1, n):
                s -= R[m, i] * x[m, c]
            x[i, c] = s / R[i, i]
    return x


@njit(cache=True)
def _spd_solve(H, g):
    """H^-1 g by :func:`_cholesky_solve`, or LAPACK's general solve where H is not positive definite to round-off."""
    x = _cholesky_solve(H, g)
    if not np.all(np.isfinite(x)):
        x = np.linalg.solve(H, g)
    return x


@njit(cache=True)
def _normal_equations(z, a, Ia, Lk, ek, u, w):
    """Gauss-Newton system (H, grad) of :func:`_pair_cost` at ``z``, with d(z) and its Jacobian L."""
    d, L = _d_and_L(z)
    d[2] = _wrap(d[2])
    H = np.zeros((6, 6))
    grad = np.zeros((6, 1))
    for i in range(6):
        for j in range(i, 6):
            h = 0.0
            for r in range(3):
                h += w[r] * L[r, i] * L[r, j]
            H[i, j] = h
        gi = 0.0
        for r in range(3):
            gi += w[r] * L[r, i] * (d[r] - u[r])
        grad[i, 0] = gi
    for i in range(3):
        for j in range(3):
            if j >= i:                               # the upper triangle; mirrored below
                H[i, j] += Ia[i, j]
                H[i + 3, j + 3] += Lk[i, j]
            grad[i, 0] += Ia[i, j] * (z[j] - a[j])
            grad[i + 3, 0] += Lk[i, j] * z[j + 3]
        grad[i + 3, 0] -= ek[i]
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
    return H, grad, d, L


@njit(cache=True)
def action_means(mu_a, P_a, Ld, ed, u_prev, act_sig, iterations=5, variance=True):
    """E[d(s_k, s_{k+1})] per step under the pairwise posterior alpha_k(s_k) delta_{k+1}(s_{k+1}) f_A(d) (eq. 6).

    f_A has the previous iteration's per-step mean ``u_prev[k]`` and covariance diag(act_sig[k]^2).
    As in the paper d is linearised and the three Gaussians multiplied in closed form, but at the
    mode of the pairwise posterior (Gauss-Newton from the action model's prediction, delta kept in
    the information form the backward filter gives) rather than at the mean of alpha * delta:
    that mean does not exist where delta is improper, which the backward filter's infinite start
    makes it on the last steps of every log, and where it is merely vague, linearising there
    sends the displacement far off (hundreds of rad per step seen). Where alpha and delta are sharp
    next to f_A the two points coincide. ``ed`` and ``Ld`` are linearised at the forward means, so s' keeps their
    heading branch. Also returns the posterior variance of each component of d (for the action-noise M-step),
    or None when ``variance`` is False (the paper's fixed Sigma_A never uses it).
    """
    n = u_prev.shape[0]
    out = np.empty((n, 3))
    var = np.zeros((n, 3)) if variance else None
    for k in range(n):
        w = 1.0 / act_sig[k] ** 2
        a = mu_a[k]
        Ia = _inv3(P_a[k])
        g0, _ = _predict_jac(a, u_prev[k])
        g0[2] = mu_a[k + 1, 2] + _wrap(g0[2] - mu_a[k + 1, 2])
        z = np.concatenate((a, g0))
        Lk, ek = Ld[k + 1], ed[k + 1]
        cost = _pair_cost(z, a, Ia, Lk, ek, u_prev[k], w)
        pred = u_prev[k].copy()
        H_best = np.zeros((6, 6))
        L_best = np.zeros((3, 6))
        moved = False
        for it in range(iterations):
            H, grad, d, L = _normal_equations(z, a, Ia, Lk, ek, u_prev[k], w)
            step = -_spd_solve(H, grad)[:, 0]
            znew = z + step
            c = _pair_cost(znew, a, Ia, Lk, ek, u_prev[k], w)
            if it > 0 and c >= cost:
                break
            cost = c
            pred = d + L @ step
            H_best, L_best, moved = H, L, True
            z = znew
        out[k] = pred
        if variance and moved:
            X = _spd_solve(H_best, np.ascontiguousarray(L_best.T))
            for r in range(3):
                v = 0.0
                for i in range(6):
                    v += L_best[r, i] * X[i, r]
                var[k, r] = v
    return out, var
