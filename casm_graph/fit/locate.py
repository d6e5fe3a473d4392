"""Where was the robot? A grid smoother over position that needs no velocities and no sensor curve.

A histogram forward-backward smoother over position with a random-walk motion model, run under a
family of physical sensor hypotheses, reading = k * d**p (p = -1: apparent size, p = +1: range); the
hypothesis with the highest evidence p(readings | hypothesis) wins, and a few EM rounds refit the curve
as a polynomial against the smoothed distances. Every log kind's start begins here when it has readings.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from casm_graph.graph import robust
from casm_graph.io.log import Log

OUTLIER_Z2 = np.float32(8.0)


@dataclass
class _Grid:
    x: np.ndarray
    y: np.ndarray
    cell: float
    dist: np.ndarray            # (L, ny, nx) distance from each cell to each landmark


def grid_cell(log: Log, finest: float = 0.1, cells: int = 150) -> float:
    """Cell of the start's grid smoother: ``finest`` metres, coarser on fields larger than ``cells`` of it
    (a plaza of beacons 70 m apart would otherwise need half a million cells per knot, and a landmark a
    thousand kilometres off, all the memory there is)."""
    return max(finest, float(np.ptp(log.landmark_xy, axis=0).max()) / cells)


def _grid(log: Log, cell: float, margin: float) -> _Grid:
    lo = log.landmark_xy.min(0) - margin
    hi = log.landmark_xy.max(0) + margin
    x = np.arange(lo[0], hi[0] + cell, cell)
    y = np.arange(lo[1], hi[1] + cell, cell)
    X, Y = np.meshgrid(x, y)
    dist = np.hypot(X[None] - log.landmark_xy[:, 0, None, None], Y[None] - log.landmark_xy[:, 1, None, None])
    return _Grid(x, y, cell, dist)


def _blur_matrix(n: int, blur: float) -> np.ndarray:
    """(n, n) Gaussian blur along one axis with zero outside the grid (mass leaving the field is lost)."""
    i = np.arange(n)
    K = np.exp(-0.5 * ((i[:, None] - i[None, :]) / blur) ** 2)
    K[np.abs(i[:, None] - i[None, :]) > max(1, int(np.ceil(3 * blur)))] = 0.0
    return K / K.sum(axis=1, keepdims=True).max()


def _log_likelihood(grid: _Grid, step_of_obs, lm_of_obs, reading, predict, sigma):
    """Steps with readings, and the (n, ny, nx) summed log-likelihood of each at every cell.

    The Gaussian term is capped at ``OUTLIER_Z2`` so a reading that fits nowhere cannot veto a cell.
    """
    pred = np.stack([predict(d) for d in grid.dist]).astype(np.float32)
    s = (np.asarray(sigma(reading), np.float32) * np.ones(len(reading), np.float32))
    order = np.argsort(step_of_obs, kind="stable")
    steps = step_of_obs[order]
    first = np.flatnonzero(np.r_[True, np.diff(steps) != 0])
    out = np.empty((len(first), *grid.dist.shape[1:]), dtype=np.float32)
    _summed_terms(pred, np.asarray(lm_of_obs, np.int64), np.asarray(reading).astype(np.float32), s,
                  order.astype(np.int64), np.append(first, len(order)).astype(np.int64), out)
    return steps[first], out


@njit(cache=True)
def _summed_terms(pred, lm, reading, s, order, bounds, out):
    """out[g] = sum over sightings order[bounds[g]:bounds[g+1]] of -0.5 min(z^2, OUTLIER_Z2) at every cell,
    z = (reading - pred[lm]) / s, in float32 and in the order numpy's ``add.reduceat`` adds them, the
    first term plus the running sum of the others (one pass over the sightings, where the array form
    made six passes over (sightings, ny, nx) arrays)."""
    cap = np.float32(OUTLIER_Z2)
    half = np.float32(-0.5)
    ny, nx = pred.shape[1], pred.shape[2]
    for g in range(len(bounds) - 1):
        lo, hi = bounds[g], bounds[g + 1]
        for k in list(range(lo + 1, hi)) + [lo]:
            j = order[k]
            r, sj, p = reading[j], s[j], pred[lm[j]]
            for y in range(ny):
                for x in range(nx):
                    z = (r - p[y, x]) / sj
                    zz = z * z
                    if zz > cap:
                        zz = cap
                    v = half * zz
                    if k == lo + 1 or (k == lo and hi == lo + 1):
                        out[g, y, x] = v
                    else:
                        out[g, y, x] += v


def _smooth(grid: _Grid, step_of_obs: np.ndarray, lm_of_obs: np.ndarray, reading: np.ndarray,
            predict, sigma, n_steps: int, blur: float, means: bool = True):
    """Histogram forward-backward smoother; returns posterior mean positions and log evidence.

    With ``means=False`` only the forward pass runs (the evidence needs nothing more).
    """
    steps, ll = _log_likelihood(grid, step_of_obs, lm_of_obs, reading, predict, sigma)
    row = np.full(n_steps, -1)
    row[steps] = np.arange(len(steps))
    shape = grid.dist.shape[1:]
    Ky, Kx = _blur_matrix(shape[0], blur), _blur_matrix(shape[1], blur).T
    alpha = np.empty((n_steps, *shape), dtype=np.float32)
    a = np.full(shape, 1.0 / np.prod(shape))
    log_ev = 0.0
    for k in range(n_steps):
        if k:
            a = Ky @ a @ Kx
        if row[k] >= 0:
            lk = ll[row[k]]
            m = float(lk.max())
            a = a * np.exp(lk - m)
            log_ev += m
        z = a.sum()
        log_ev += np.log(z)
        a /= z
        alpha[k] = a
    if not means:
        return None, log_ev
    mean = np.empty((n_steps, 2))
    b = np.ones(shape)
    X, Y = np.meshgrid(grid.x, grid.y)
    for k in range(n_steps - 1, -1, -1):
        if k < n_steps - 1:
            if row[k + 1] >= 0:
                lk = ll[row[k + 1]]
                b = b * np.exp(lk - lk.max())
            b = Ky @ b @ Kx
            b /= b.max()
        g = alpha[k] * b
        g /= g.sum()
        mean[k] = ((g * X).sum(), (g * Y).sum())
    return mean, log_ev


@dataclass
class Located:
    """Step 1's answer: smoothed positions at the knots and the sensor curve fitted against them."""

    mean: np.ndarray            # (K, 2) posterior mean position at each knot
    poly: np.ndarray            # reading polynomial against the smoothed distances
    residual: np.ndarray        # reading residuals under ``poly``
    hypothesis: tuple[float, float]
    log_evidence: float


def locate(log: Log, obs_knot: np.ndarray, n_knots: int, dt_k: float, c_knot: np.ndarray, n_c_knots: int,
           degree: int, cell: float = 0.1, speed: float = 0.6) -> Located:
    """Step 1: where was the robot at each knot, with no velocities and an unknown sensor curve.

    ``obs_knot`` maps observations to knots ``dt_k`` seconds apart; ``c_knot`` maps them to the
    coarser knots (about 3 ``dt_k`` apart) on which the hypotheses are scored. ``speed`` (m/s) sets
    the random walk; it should exceed how fast the robot moves.
    """
    has_r = ~np.isnan(log.obs_reading)
    lm_idx = log.landmark_index
    grid = _grid(log, cell, margin=1.5)
    blur = speed * dt_k / cell       # random walk of ~0.6 m/s: faster than a walking Aibo
    reading = log.obs_reading[has_r]
    r_med = float(np.median(reading))
    r_scale = float(np.median(np.abs(reading - r_med))) + 1e-9
    args = (obs_knot[has_r], lm_idx[has_r], reading)

    # sensor hypotheses reading = k d^p, scored by evidence on a coarser grid (3x stride, 2x cell)
    c_cell = 2 * cell
    c_grid = _grid(log, c_cell, margin=1.5)
    c_blur = speed * dt_k * 3 / c_cell
    c_args = (c_knot[has_r], lm_idx[has_r], reading)
    d_typ = np.geomspace(0.5, 2.0 * np.ptp(log.landmark_xy, axis=0).max() + 0.5, 10)
    best = None
    for p in (-1.0, 1.0):
        for dt_ in d_typ:
            k = r_med / dt_ ** p
            _, ev = _smooth(c_grid, *c_args, lambda d, k=k, p=p: k * d ** p,
                            lambda r: 0.15 * abs(r) + 0.1 * r_scale, n_c_knots, c_blur,
                            means=False)
            if best is None or ev > best[2]:
                best = (p, k, ev)
    p, k, ev = best
    mean, ev = _smooth(grid, *args, lambda d: k * d ** p, lambda r: 0.15 * abs(r) + 0.1 * r_scale,
                       n_knots, blur)
    # EM rounds: refit the curve as a polynomial against the smoothed distances
    lm = log.landmark_xy[lm_idx]
    for _ in range(2):
        d_obs = np.hypot(*(mean[obs_knot] - lm).T)
        poly = robust.polyfit(d_obs[has_r], reading, degree)
        res = reading - np.polynomial.polynomial.polyval(d_obs[has_r], poly)
        s = 1.4826 * np.median(np.abs(res)) + 1e-9
        lo, hi = np.percentile(d_obs[has_r], [1, 99])
        predict = (lambda d, poly=poly, lo=lo, hi=hi:
                   np.polynomial.polynomial.polyval(np.clip(d, lo, hi), poly))
        mean, ev = _smooth(grid, *args, predict, lambda r, s=s: 2.0 * s, n_knots, blur)
    d_obs = np.hypot(*(mean[obs_knot] - lm).T)
    poly = robust.polyfit(d_obs[has_r], reading, degree)
    return Located(mean, poly, res, (p, k), float(ev))


