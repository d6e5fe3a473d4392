"""Initialisation from nothing but the log and the map, free of local minima.

Plain LM from zero velocities and a poor sensor model lands in a wrong minimum, so the start is
built in three global steps before any least squares runs:

1. **Where was the robot?** A histogram (grid) forward-backward smoother over position with a
   random-walk motion model needs no velocities. The sensor curve is unknown, so it is run under
   a family of physical hypotheses, reading = k * d**p (p = -1: apparent size, p = +1: range), and
   the hypothesis with the highest evidence p(readings | hypothesis) wins; a few EM rounds then
   refit the curve as a polynomial against the smoothed distances.
2. **Which way did it face?** Within each constant-action segment the heading is theta0 + w t; a
   circular regression of (direction to landmark - measured bearing) on time gives theta0 and w.
   With ranges only (no bearing anywhere) the heading shows only through the motion
   (:func:`_motion_headings`): each segment's smoothed positions are fitted by an arc, which gives
   its direction of travel and, through the curvature, its action's turn rate; the headings are
   chained across segments by synchronising the actions' directions of travel in the body frame.
3. **How fast?** With the headings fixed, the segment's positions are linear in its body-frame
   velocity; per-action averages of the per-segment fits give the starting table, and dead
   reckoning each segment from its own fit gives the starting trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from casm_graph.fit.locate import grid_cell, locate
from casm_graph.fit.windows import curve_at, inverse_curve, window_start
from casm_graph.graph import robust
from casm_graph.io.log import Log, LogError, wrap
from casm_graph.models.model import Model
from factors.reading import slope as curve_slope

@dataclass
class Start:
    """The initial guess: poses at every pose step, the model, and what the search found."""

    poses: np.ndarray           # (T+1, 3)
    model: Model
    hypothesis: tuple[float, float]   # (p, k) of the winning sensor hypothesis
    log_evidence: float
    heading_agreement: float = float("nan")   # ranges only: how well the chained headings agree (1: fully;
                                              # NaN: bearings gave them, or too few repeated moves to tell)


def _headings(seg_of_knot, seg_act, t_knot, obs_knot, dirs, bearing, w_max=3.0):
    """Circular regression of heading samples on time: (theta0 at segment start, w) per segment.

    Segments of the same action share one turn rate, so w is chosen per action by maximising the
    summed resultant lengths of its segments; each segment keeps its own theta0.
    """
    n_seg = len(seg_act)
    theta_obs = wrap(dirs - bearing)
    ws = np.linspace(-w_max, w_max, 1201)
    seg_obs = seg_of_knot[obs_knot]
    # seg_of_knot is non-decreasing: each segment's knots (and, sorted stably, its sightings) are one slice
    first = np.searchsorted(seg_of_knot, np.arange(n_seg))
    t0 = t_knot[np.minimum(first, len(t_knot) - 1)]   # a run too short to hold a knot has no sighting either
    tt = t_knot[obs_knot] - t0[seg_obs]
    by_seg = np.argsort(seg_obs, kind="stable")
    cut = np.searchsorted(seg_obs[by_seg], np.arange(n_seg + 1))
    out = np.full((n_seg, 2), np.nan)
    for a in np.unique(seg_act):
        segs = np.flatnonzero(seg_act == a)
        sums = []
        for s in segs:
            sel = by_seg[cut[s]:cut[s + 1]]
            sums.append(np.exp(1j * (theta_obs[sel][None, :] - ws[:, None] * tt[sel][None, :])).sum(axis=1))
        sums = np.array(sums)
        if sums.size == 0 or not np.any(np.abs(sums)):
            continue
        i = np.argmax(np.abs(sums).sum(axis=0))
        for s, z in zip(segs, sums[:, i]):
            if abs(z) > 0:
                out[s] = (np.angle(z), ws[i])
    return out


TURN_RATES = np.linspace(-4.0, 4.0, 401)    # rad/s: the turn rates a ranges-only start tries per action
MIN_REDUNDANCY = 10                          # links beyond the unknowns they determine, to judge how well they agree
MOVING = 25.0                                # chi-square gain of an arc over standing still that counts as moving


def _arc_basis(tt: np.ndarray, ws: np.ndarray) -> np.ndarray:
    """(len(ws), len(tt)) complex g_w(t) = (exp(i w t) - 1) / (i w): an arc's displacement per unit velocity."""
    w = np.where(ws == 0, 1.0, ws)[:, None]
    return np.where(ws[:, None] == 0, tt[None, :], (np.exp(1j * w * tt[None, :]) - 1) / (1j * w))


def _range_arcs(lm: np.ndarray, dist: np.ndarray, weight: np.ndarray, tt: np.ndarray, ws: np.ndarray,
                z: np.ndarray, tz: np.ndarray, iterations: int = 8):
    """One segment's arc p(t) = z0 + u g_w(t) fitted to its ranges for every turn rate in ``ws`` (Gauss-Newton,
    Huber-weighted, started from the arc through the smoothed positions ``z`` at times ``tz``).

    ``dist`` are the ranges as distances, ``weight`` their inverse variances. Returns z0, u and the weighted
    residual sum of squares per turn rate, and that sum for a robot standing still at its best point.
    """
    g = _arc_basis(tz, ws)
    gc, zc = g - g.mean(axis=1, keepdims=True), z - z.mean()
    u = np.sum(np.conj(gc) * zc[None, :], axis=1) / np.maximum(np.sum(np.abs(gc) ** 2, axis=1), 1e-12)
    z0 = z.mean() - u * g.mean(axis=1)
    sw = np.sqrt(weight)[None, :]
    p, rss = _arc_gauss_newton(np.column_stack([z0.real, z0.imag, u.real, u.imag]), _arc_basis(tt, ws), lm, dist,
                               sw, iterations)
    still = int(np.argmin(np.abs(ws)))            # standing still: the same fit with no displacement at all
    _, rss0 = _arc_gauss_newton(np.array([[p[still, 0], p[still, 1], 0.0, 0.0]]), np.zeros((1, len(tt)), complex),
                                lm, dist, sw, iterations)
    return p[:, 0] + 1j * p[:, 1], p[:, 2] + 1j * p[:, 3], rss, float(rss0[0])


def _arc_gauss_newton(p: np.ndarray, g: np.ndarray, lm: np.ndarray, dist: np.ndarray, sw: np.ndarray,
                      iterations: int):
    """Huber-weighted Gauss-Newton of arcs (z0 real, imag, u real, imag), one per row of the basis ``g``, on
    ranges ``dist`` to ``lm`` whitened by ``sw``: the parameters and each arc's weighted residual sum of squares."""
    gr, gi = g.real, g.imag
    for it in range(iterations + 1):
        px = p[:, :1] + p[:, 2:3] * gr - p[:, 3:4] * gi
        py = p[:, 1:2] + p[:, 2:3] * gi + p[:, 3:4] * gr
        dx, dy = px - lm[None, :, 0], py - lm[None, :, 1]
        d = np.maximum(np.hypot(dx, dy), 1e-9)
        r = (d - dist[None, :]) * sw
        if it == iterations:
            break
        h = robust.huber(r)
        ex, ey = dx / d * sw * h, dy / d * sw * h
        J = np.stack([ex, ey, ex * gr + ey * gi, -ex * gi + ey * gr], axis=-1)
        H = np.einsum("wni,wnj->wij", J, J) + 1e-9 * np.eye(4)
        p = p - np.linalg.solve(H, np.einsum("wni,wn->wi", J, r * h)[..., None])[..., 0]
    return p, np.sum(robust.huber_loss(r), axis=1) * 2


def _motion_headings(seg_act, seg_t, t_ref, seg_u, seg_rss, rss0, model: Model, attempted=None):
    """Headings and turn rates of every constant-action segment from its arcs (ranges only).

    ``seg_u`` (segments, turn rates) is each segment's complex velocity at its reference time ``t_ref``
    (NaN: too few ranges to fit), ``seg_rss`` its weighted misfit and ``rss0`` the misfit standing still.
    An action's turn rate is where its segments' summed misfit is least (curvature) when it moves; one
    that barely moves gets its turn rate from how the direction of travel turns across it. The heading
    is arg(u) - phi_a, phi_a the action's direction of travel in the body frame; phi_a and the turn rates
    are chosen to make consecutive moving segments agree (angular synchronisation by the leading
    eigenvector, then coordinate ascent). One rotation is free (every heading + d, every body velocity by
    -d: ranges and motion unchanged): it is fixed so the actions travel along their attempted directions
    (actions.csv) when known, else so the most-travelled action moves straight ahead.

    Returns (theta at t_ref, w) per segment, the chosen turn-rate index per action, and how well the
    moving segments' headings agree once chained (the mean resultant length of the links' misses, 0 to 1;
    NaN when too few links repeat to tell).
    """
    n_seg, A = len(seg_act), len(model.action_ids)
    ws = TURN_RATES
    fitted = np.isfinite(t_ref)
    rss = np.zeros((A, len(ws)))
    np.add.at(rss, seg_act[fitted], seg_rss[fitted])
    best = np.argmin(rss, axis=1)
    dur = np.diff(seg_t)
    gain = np.where(fitted, rss0 - seg_rss[np.arange(n_seg), best[seg_act]], 0.0)
    mover_action = np.zeros(A, bool)
    for a in range(A):
        sel = fitted & (seg_act == a)
        mover_action[a] = sel.any() and np.median(gain[sel]) > MOVING
    wi = np.where(mover_action, best, int(np.argmin(np.abs(ws))))
    movers = np.flatnonzero(fitted & mover_action[seg_act] & (gain > MOVING))
    if len(movers) < 2:
        return np.column_stack([np.zeros(n_seg), ws[wi][seg_act]]), wi, 0.0

    # links between consecutive moving segments: arg u_s' - arg u_s = phi_a' - phi_a + sum of w_a x time in a
    L = len(movers) - 1
    dur_in = np.zeros((L, A))
    for i in range(L):
        s, s2 = movers[i], movers[i + 1]
        dur_in[i, seg_act[s]] += seg_t[s + 1] - t_ref[s]
        np.add.at(dur_in[i], seg_act[s + 1:s2], dur[s + 1:s2])
        dur_in[i, seg_act[s2]] += t_ref[s2] - seg_t[s2]
    a0, a1 = seg_act[movers[:-1]], seg_act[movers[1:]]
    phi = np.zeros(A)
    ang = np.angle(seg_u[movers])                                   # (M, len(ws)) direction of travel
    rows = np.arange(len(movers))
    d = ang[rows, wi[seg_act[movers]]]
    turning = np.flatnonzero((dur_in.sum(axis=0) > 0) & ~mover_action)    # turn rates the links must find
    through = dur_in[:, turning] > 0
    # first the directions of travel from links through moving actions only, then each turning action's rate
    # from the links through it alone, then everything in turn
    plain = ~through.any(axis=1)
    M = np.zeros((A, A), complex)
    np.add.at(M, (a1[plain], a0[plain]), np.exp(1j * (np.diff(d) - dur_in @ ws[wi])[plain]))
    phi = np.angle(np.linalg.eigh(M + M.conj().T)[1][:, -1])

    def turn_rate(a: int, links: np.ndarray) -> int:
        """The turn rate of action ``a`` on which ``links`` agree best, the rest held."""
        miss = (np.diff(d) - (phi[a1] - phi[a0]) - dur_in @ ws[wi])[links]
        return int(np.argmax(np.sum(np.cos(miss[None, :] - (ws - ws[wi[a]])[:, None] * dur_in[None, links, a]),
                                    axis=1)))

    for k, a in enumerate(turning):
        alone = through[:, k] & (through.sum(axis=1) == 1)
        if alone.sum() >= 2:
            wi[a] = turn_rate(a, alone)
    for sweep in range(8):
        delta = np.diff(d) - dur_in @ ws[wi]                       # phi_a1 - phi_a0 wanted
        for _ in range(5):
            z = np.zeros(A, complex)
            np.add.at(z, a1, np.exp(1j * (phi[a0] + delta)))
            np.add.at(z, a0, np.exp(1j * (phi[a1] - delta)))
            phi = np.where(np.abs(z) > 0, np.angle(z), phi)
        for a in turning:
            wi[a] = turn_rate(a, np.ones(L, bool))
    w = ws[wi]
    d = ang[rows, wi[seg_act[movers]]]
    agreement = float(np.abs(np.mean(np.exp(1j * (np.diff(d) - (phi[a1] - phi[a0]) - dur_in @ w)))))
    if L - (len(np.unique(np.concatenate([a0, a1]))) - 1) - len(turning) < MIN_REDUNDANCY:
        agreement = float("nan")                     # as many unknowns as links: any chain agrees

    # the free rotation: attempted directions of travel when known, else the most-travelled action straight ahead
    weight = np.bincount(seg_act[movers], weights=np.abs(seg_u[movers, wi[seg_act[movers]]]) * dur[movers],
                         minlength=A)
    shift = -phi[int(np.argmax(weight))]
    if attempted is not None:
        ok = np.isfinite(attempted[:, 0]) & (np.hypot(attempted[:, 0], attempted[:, 1]) > 0) & (weight > 0)
        if ok.any():
            shift = np.angle(np.sum(weight[ok] * np.exp(1j * (np.arctan2(attempted[ok, 1], attempted[ok, 0])
                                                             - phi[ok]))))
    phi = phi + shift

    # headings: each segment carries the offset of the nearest moving segment along the dead-reckoned heading
    start_heading = np.concatenate([[0.0], np.cumsum(w[seg_act] * dur)])[:-1]
    t_at = np.where(fitted, t_ref, seg_t[:-1])
    dead = start_heading + w[seg_act] * (t_at - seg_t[:-1])          # dead-reckoned heading at each t_at
    offset = wrap(d - phi[seg_act[movers]] - dead[movers])
    mid = 0.5 * (seg_t[:-1] + seg_t[1:])
    i = np.searchsorted(mid[movers], mid)
    after, before = np.clip(i, 0, len(movers) - 1), np.clip(i - 1, 0, len(movers) - 1)
    pick = np.where(np.abs(mid[movers[before]] - mid) < np.abs(mid[movers[after]] - mid), before, after)
    return np.column_stack([wrap(dead + offset[pick]), w[seg_act]]), wi, agreement


def _range_start(log: Log, model: Model, seg_start, seg_of_knot, seg_act, t_knot, mean, poly, res):
    """Headings and turn rates per segment (as :func:`_headings` gives them from bearings) from ranges alone, and
    the knots' positions replaced, segment by segment, by the arc its ranges chose (the grid smoother's
    positions wander by tens of centimetres; an arc of constant velocity averages a segment's ranges)."""
    T, n_seg = log.steps, len(seg_start)
    t_pose = log.pose_times
    seg_t = np.append(t_pose[seg_start], t_pose[T])
    d_max = 1.5 * float(np.max(np.hypot(*(log.landmark_xy[:, None] - log.landmark_xy[None]).transpose(2, 0, 1))))
    lm = log.landmark_xy[log.landmark_index]
    by_step = np.argsort(log.obs_step, kind="stable")
    seg_of_obs = np.clip(np.searchsorted(seg_start, log.obs_step[by_step], side="right") - 1, 0, n_seg - 1)
    knot_cut = np.searchsorted(seg_of_knot, np.arange(n_seg + 1))
    obs_cut = np.searchsorted(seg_of_obs, np.arange(n_seg + 1))
    attempted = (np.array([log.attempted.get(int(a), np.full(3, np.nan)) for a in model.action_ids])
                 if log.attempted else None)
    dist = inverse_curve(poly, 0.05, max(d_max, 1.0), model.reading_basis)(log.obs_reading)
    slope = np.abs(curve_slope(dist, poly, model.reading_basis))
    weight = (slope / max(1.4826 * float(np.median(np.abs(res))), 1e-9)) ** 2   # inverse variance as a distance
    t_ref = np.full(n_seg, np.nan)
    nw = len(TURN_RATES)
    seg_z0, seg_u = np.full((n_seg, nw), np.nan, complex), np.full((n_seg, nw), np.nan, complex)
    seg_rss, rss0 = np.zeros((n_seg, nw)), np.zeros(n_seg)
    for s in range(n_seg):
        kn, ob = np.arange(knot_cut[s], knot_cut[s + 1]), by_step[obs_cut[s]:obs_cut[s + 1]]
        if len(kn) < 3 or len(ob) < 6:
            continue
        t_ref[s] = t_knot[kn[0]]
        seg_z0[s], seg_u[s], seg_rss[s], rss0[s] = _range_arcs(
            lm[ob], dist[ob], weight[ob], log.obs_t[ob] - t_ref[s], TURN_RATES,
            mean[kn, 0] + 1j * mean[kn, 1], t_knot[kn] - t_ref[s])
    head, wi, agreement = _motion_headings(seg_act, seg_t, t_ref, seg_u, seg_rss, rss0, model, attempted)
    mean = mean.copy()
    for s in np.flatnonzero(np.isfinite(t_ref)):
        kn = np.arange(knot_cut[s], knot_cut[s + 1])
        j = wi[seg_act[s]]
        z = seg_z0[s, j] + seg_u[s, j] * _arc_basis(t_knot[kn] - t_ref[s], TURN_RATES[j:j + 1])[0]
        mean[kn] = np.column_stack([z.real, z.imag])
    return head, mean, agreement


def _bearing_start(log: Log, model: Model, knots: np.ndarray) -> np.ndarray:
    """Positions at ``knots`` from bearings alone (the headings then come from the bearings as with readings):
    the window start (:func:`casm_graph.fit.windows.window_start`, triangulation along the path) dead-reckoned
    with actions.csv's attempted velocities, the only velocity scale such a log has."""
    if not log.attempted or any(int(a) not in log.attempted for a in model.action_ids):
        raise LogError("actions.csv: an action-table log with bearings only needs every action's attempted "
                       "velocity (columns vx_cmd,vy_cmd,w_cmd) for its start; give actions.csv or readings")
    nominal = np.array([log.attempted[int(a)] for a in log.action], float)
    speed = 2.0 * float(np.max(np.hypot(nominal[:, 0], nominal[:, 1]), initial=0.05))
    ws = window_start(log, nominal, len(model.reading_poly), max(speed, 0.05))
    return ws.poses[knots, :2]


def initialise(log: Log, model: Model, stride: int = 5, cell: float | None = None) -> Start:
    """Global start for ``calibrate``: trajectory, velocity table and sensor polynomial (``cell``: the grid
    smoother's, by default :func:`casm_graph.fit.locate.grid_cell`)."""
    cell = grid_cell(log) if cell is None else cell
    T = log.steps
    knots = np.arange(0, T + 1, stride)
    t_pose = log.pose_times
    t_knot = t_pose[knots]
    obs_knot = np.clip(np.round(log.obs_step / stride).astype(int), 0, len(knots) - 1)
    lm_idx = log.landmark_index
    lm = log.landmark_xy[lm_idx]
    if "reading" not in log.channels:
        mean = _bearing_start(log, model, knots)
        poly, res, (p, k), ev = np.asarray(model.reading_poly, float), None, (np.nan, np.nan), np.nan
    else:
        c_stride = 3 * stride
        c_knot = np.clip(np.round(log.obs_step / c_stride).astype(int), 0, T // c_stride)
        loc = locate(log, obs_knot, len(knots), float(np.median(np.diff(t_knot))), c_knot, T // c_stride + 1,
                     len(model.reading_poly) - 1, cell)
        mean, poly, res, (p, k), ev = loc.mean, loc.poly, loc.residual, loc.hypothesis, loc.log_evidence
        if model.reading_basis != "distance":        # the curve the user asked for, at the located distances
            poly, res = curve_at(log, mean[obs_knot], len(poly) - 1, model.reading_basis)

    # 2. headings per constant-action segment from bearings
    act = log.action
    seg_start = np.concatenate([[0], np.flatnonzero(np.diff(act) != 0) + 1])
    seg_of_step = np.cumsum(np.isin(np.arange(T), seg_start)) - 1
    seg_of_knot = seg_of_step[np.minimum(knots, T - 1)]
    n_seg = len(seg_start)
    has_b = ~np.isnan(log.obs_bearing)
    dirs = np.arctan2(lm[:, 1] - mean[obs_knot, 1], lm[:, 0] - mean[obs_knot, 0])
    seg_act = model.action.rows_of(act[seg_start])
    agreement = float("nan")
    if has_b.any():
        head = _headings(seg_of_knot, seg_act, t_knot, obs_knot[has_b], dirs[has_b], log.obs_bearing[has_b])
    else:
        head, mean, agreement = _range_start(log, model, seg_start, seg_of_knot, seg_act, t_knot, mean, poly, res)

    # 3. body-frame velocity per segment, then per action
    seg_v = np.full((n_seg, 3), np.nan)
    knot_cut = np.searchsorted(seg_of_knot, np.arange(n_seg + 1))      # seg_of_knot is non-decreasing
    for s in range(n_seg):
        sel = np.arange(knot_cut[s], knot_cut[s + 1])
        if len(sel) < 3 or np.isnan(head[s, 0]):
            continue
        tt = t_knot[sel] - t_knot[sel[0]]
        th0, w = head[s]
        # integral of R(th0 + w tau) d tau from 0 to t, by the trapezoid rule on a fine grid
        tau = np.linspace(0, tt[-1], 8 * len(tt))
        c, sn = np.cos(th0 + w * tau), np.sin(th0 + w * tau)
        ic = np.concatenate([[0], np.cumsum((c[1:] + c[:-1]) / 2 * np.diff(tau))])
        is_ = np.concatenate([[0], np.cumsum((sn[1:] + sn[:-1]) / 2 * np.diff(tau))])
        ic, is_ = np.interp(tt, tau, ic), np.interp(tt, tau, is_)
        n = len(sel)
        A = np.zeros((2 * n, 4))
        A[0::2, 0] = 1
        A[1::2, 1] = 1
        A[0::2, 2], A[0::2, 3] = ic, -is_
        A[1::2, 2], A[1::2, 3] = is_, ic
        sol, *_ = np.linalg.lstsq(A, mean[sel].reshape(-1), rcond=None)
        seg_v[s] = (sol[2], sol[3], w)

    vel = np.zeros_like(model.velocities)
    for a in range(len(model.action_ids)):
        rows = seg_v[(seg_act == a) & ~np.isnan(seg_v[:, 0])]
        if len(rows):
            vel[a] = np.median(rows, axis=0)

    # trajectory: each segment dead-reckoned from its own start with its own fit
    poses = np.empty((T + 1, 3))
    dt = log.dt
    for s in range(n_seg):
        a0 = seg_start[s]
        a1 = seg_start[s + 1] if s + 1 < n_seg else T
        v = seg_v[s] if not np.isnan(seg_v[s, 0]) else vel[seg_act[s]]
        th0 = head[s, 0] if not np.isnan(head[s, 0]) else 0.0
        kk = np.clip(np.round(np.arange(a0, a1 + 1) / stride).astype(int), 0, len(knots) - 1)
        th = th0 + v[2] * (t_pose[a0:a1 + 1] - t_pose[a0])
        c, sn = np.cos(th[:-1]), np.sin(th[:-1])
        x = mean[kk[0], 0] + np.concatenate([[0], np.cumsum((c * v[0] - sn * v[1]) * dt[a0:a1])])
        y = mean[kk[0], 1] + np.concatenate([[0], np.cumsum((sn * v[0] + c * v[1]) * dt[a0:a1])])
        poses[a0:a1 + 1] = np.column_stack([x, y, wrap(th)])

    out = model.with_(velocities=vel, reading_poly=poly, reading_sigma=(
        model.reading_sigma if res is None else float(max(1.4826 * np.median(np.abs(res)), 1e-6))))
    return Start(poses=poses, model=out, hypothesis=(p, k), log_evidence=float(ev), heading_agreement=agreement)
