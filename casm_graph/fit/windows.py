"""The global start of a log from windows of sightings along nominal dead reckoning.

Every log kind shares it: continuous commands give the nominal body velocity of each step (velocity =
command), action tables the attempted velocity of each action (actions.csv). Then:

1. where readings exist, the sensor hypothesis (reading = k d**p) by the evidence of the grid smoother
   of :func:`casm_graph.fit.locate.locate`; a range (p = +1) starts as the line reading = k d, its
   slope chosen among ``slope_factors`` by how well the windows agree; any other power (an apparent
   size, p = -1) gives each sighting's distance through k d**p itself;
2. each window with three or more sightings is placed at every candidate start heading, its sightings
   along the window's dead-reckoned path: range and bearing (:func:`range_bearing_fits`), ranges only
   (:func:`window_pose_ranges`, multilateration; the heading shows through the motion alone) or
   bearings only (:func:`bearing_fits`, triangulation);
3. the headings are chained across windows by dynamic programming against the dead-reckoned moves
   (:func:`chain_headings`), and the trajectory dead-reckoned from window to window.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

import factors.command
from casm_graph.fit.locate import grid_cell, locate
from casm_graph.fit.residuals import distances
from casm_graph.graph import robust
from casm_graph.graph import table as G
from casm_graph.io.log import Log, wrap
from casm_graph.models.model import Model
from factors.reading import curve

MIN_BOTH = 10                # sightings with reading and bearing below which a log is placed by one channel


@dataclass(frozen=True)
class WindowOptions:
    """How the window start searches; recorded with the fit that used it."""

    knot_dt: float = 0.5                  # s between the grid smoother's knots
    window: float | None = None           # s per window; None: 5 s, 20 s with ranges only (Plaza 1: 5 s windows,
                                          # about 5 m against 0.5 m range errors, started headings a radian off)
    cell: float | None = None             # m per grid cell; None: 0.1 m, coarser on large fields (``grid_cell``)
    slope_factors: tuple[float, ...] = tuple(np.geomspace(0.75, 1.33, 15))   # range-line slopes tried, relative
                                          # to the sensor hypothesis's
    slope_starts: int = 3                 # range slopes whose windows agree best, each taken on by the fit (MRCLAM
                                          # robot 4: the best-agreeing slope led to a speed map 22 % off; the
                                          # likeliest of three after the held coarse rounds, to 6.5 %)
    bearing_spread: float = 0.05          # rad: the angular miss a triangulated window is scored in

    def window_for(self, mode: str) -> float:
        return self.window if self.window is not None else 20.0 if mode == "range" else 5.0


def options_json(o: WindowOptions) -> dict:
    """``o`` as model.json records it (with the channels' windows resolved)."""
    return {"knot_dt": o.knot_dt, "window": o.window, "cell": o.cell,
            "slope_factors": [round(float(f), 6) for f in o.slope_factors], "slope_starts": o.slope_starts,
            "bearing_spread": o.bearing_spread}


@dataclass
class WindowStart:
    """The start: poses at every step, the sensor curve, and what the search found."""

    poses: np.ndarray            # (T+1, 3)
    poly: np.ndarray
    reading_sigma: float         # NaN without readings
    hypothesis: tuple[float, float]
    log_evidence: float
    windows_placed: float        # fraction of windows whose start pose the sightings fixed
    slope: float = float("nan")  # a range sensor's start slope (reading = slope d)
    alternatives: list = field(default_factory=list)   # runner-up range slopes' starts, best agreement first
    model: Model | None = None   # the start model, when the caller attached one (``with_model``)


def curve_at(log: Log, poses_at_obs: np.ndarray, degree: int, basis: str) -> tuple[np.ndarray, np.ndarray]:
    """The sensor curve in ``basis`` (robust fit) through the readings at their distances from
    ``poses_at_obs``, and the readings' residuals: a start's curve in the basis the user asked."""
    ok = np.isfinite(log.obs_reading)
    d = distances(poses_at_obs, log)[ok]
    poly = robust.polyfit(d, log.obs_reading[ok], degree, basis)
    return poly, log.obs_reading[ok] - curve(d, poly, basis)


def with_model(ws: WindowStart, model: Model, log: Log) -> WindowStart:
    """``ws`` and its alternatives carrying ``model`` with their own sensor curve and reading sigma (the
    curve refitted at their poses from ``log`` when ``model``'s basis is not the distance)."""
    def one(w):
        poly, sigma = w.poly, w.reading_sigma
        if model.reading_basis != "distance" and model.has("reading"):
            poly, res = curve_at(log, w.poses[log.obs_step], len(w.poly) - 1, model.reading_basis)
            sigma = robust.mad_scale(res)
        m = model.with_(reading_poly=poly)
        if np.isfinite(sigma):
            m = m.with_(reading_sigma=sigma)
        return replace(w, model=m, alternatives=[])
    return replace(one(ws), alternatives=[one(a) for a in ws.alternatives])


def dead_reckon_steps(velocity: np.ndarray, dt: np.ndarray, start: np.ndarray, lead: float = 0.0) -> np.ndarray:
    """(n+1, 3) poses integrating body velocities (n, 3) over steps ``dt`` from ``start``, each step along its
    heading ``lead`` of its turn on (:func:`factors.command.turned`)."""
    poses = G.integrate(start, factors.command.turned(velocity * dt[:, None], lead))
    poses[:, 2] = wrap(poses[:, 2])
    return poses


def inverse_curve(poly: np.ndarray, lo: float, hi: float, basis: str = "distance"):
    """Distance as a function of the reading, by interpolation on the monotone part of the curve ``poly``."""
    d = np.linspace(lo, hi, 400)
    r = curve(d, poly, basis)
    keep = np.flatnonzero(np.diff(r) > 0) if r[-1] > r[0] else np.flatnonzero(np.diff(r) < 0)
    d, r = d[keep], r[keep]
    order = np.argsort(r)
    return lambda z: np.interp(z, r[order], d[order])


def range_bearing_fits(fix_lm: np.ndarray, dist: np.ndarray, bearing: np.ndarray, rel: np.ndarray,
                       headings: np.ndarray, spread: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Window start positions (H, 2) and their costs (H,) for every candidate start heading, from range and bearing.

    Sighting i, taken after the robot moved ``rel[i]`` = (dx, dy, dtheta) in the window-start frame,
    places the window start at landmark - dist * u(theta0 + dtheta + bearing) - R(theta0) (dx, dy);
    each heading's position is the median placement, its cost the placements' spread (summed capped
    squares in ``spread`` units).
    """
    th = headings[:, None] + rel[None, :, 2] + bearing[None, :]
    c0, s0 = np.cos(headings)[:, None], np.sin(headings)[:, None]
    x = fix_lm[None, :, 0] - dist * np.cos(th) - (c0 * rel[None, :, 0] - s0 * rel[None, :, 1])
    y = fix_lm[None, :, 1] - dist * np.sin(th) - (s0 * rel[None, :, 0] + c0 * rel[None, :, 1])
    mx, my = np.median(x, axis=1, keepdims=True), np.median(y, axis=1, keepdims=True)
    cost = np.minimum(((x - mx) ** 2 + (y - my) ** 2) / spread ** 2, 9.0).sum(axis=1)
    return np.column_stack([mx[:, 0], my[:, 0]]), cost


def window_pose_ranges(fix_lm: np.ndarray, dist: np.ndarray, rel: np.ndarray, headings: np.ndarray,
                       guess: np.ndarray, spread: float, iterations: int = 6):
    """Start pose of one window from ranges alone: multilateration for every candidate start heading.

    Sighting i, taken after the robot moved ``rel[i]`` in the window-start frame, puts the window
    start p0 on the circle |landmark - p0 - R(theta0) (dx, dy)| = dist; for each theta0, p0 is found by
    Gauss-Newton from ``guess`` (Huber-weighted at ``spread``); the heading whose circles agree best
    wins. The heading is seen only through the motion within the window (the caller checks there is some).
    """
    H = len(headings)
    c0, s0 = np.cos(headings)[:, None], np.sin(headings)[:, None]
    cx = fix_lm[None, :, 0] - (c0 * rel[None, :, 0] - s0 * rel[None, :, 1])
    cy = fix_lm[None, :, 1] - (s0 * rel[None, :, 0] + c0 * rel[None, :, 1])
    p = np.tile(np.asarray(guess, float)[:2], (H, 1))
    for _ in range(iterations):
        dx, dy = cx - p[:, :1], cy - p[:, 1:]
        r = np.maximum(np.hypot(dx, dy), 1e-9)
        res = r - dist[None, :]
        wgt = np.minimum(1.0, 2.0 * spread / np.maximum(np.abs(res), 1e-12))
        jx, jy = -dx / r, -dy / r
        a11, a12, a22 = (wgt * jx * jx).sum(1), (wgt * jx * jy).sum(1), (wgt * jy * jy).sum(1)
        b1, b2 = -(wgt * jx * res).sum(1), -(wgt * jy * res).sum(1)
        a11, a22 = a11 + 1e-6, a22 + 1e-6
        det = a11 * a22 - a12 ** 2
        p[:, 0] += (a22 * b1 - a12 * b2) / det
        p[:, 1] += (a11 * b2 - a12 * b1) / det
    res = np.hypot(cx - p[:, :1], cy - p[:, 1:]) - dist[None, :]
    cost = np.minimum(res ** 2 / spread ** 2, 9.0).sum(axis=1)
    i = int(np.argmin(cost))
    return np.array([p[i, 0], p[i, 1], headings[i]]), float(cost[i])


def bearing_fits(fix_lm: np.ndarray, bearing: np.ndarray, rel: np.ndarray, headings: np.ndarray,
                 spread: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Window start positions (H, 2) and their costs (H,) for every candidate start heading, from bearings alone.

    For each start heading theta0, sighting i's ray leaves the robot's position p0 + R(theta0) (dx, dy)
    at the angle theta0 + dtheta + bearing and must pass through its landmark: least squares in p0 on
    the rays' normals, weighted by the inverse distance (a bearing error moves a far ray further); the
    cost sums the angular misses in ``spread`` (rad) units, capped, and penalises landmarks behind the robot.
    """
    th = headings[:, None] + rel[None, :, 2] + bearing[None, :]
    nx, ny = -np.sin(th), np.cos(th)
    c0, s0 = np.cos(headings)[:, None], np.sin(headings)[:, None]
    qx = fix_lm[None, :, 0] - (c0 * rel[None, :, 0] - s0 * rel[None, :, 1])
    qy = fix_lm[None, :, 1] - (s0 * rel[None, :, 0] + c0 * rel[None, :, 1])
    rhs = nx * qx + ny * qy
    wgt = np.ones_like(rhs)
    for _ in range(2):
        a11, a12, a22 = (wgt * nx * nx).sum(1) + 1e-9, (wgt * nx * ny).sum(1), (wgt * ny * ny).sum(1) + 1e-9
        b1, b2 = (wgt * nx * rhs).sum(1), (wgt * ny * rhs).sum(1)
        det = a11 * a22 - a12 ** 2
        px, py = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
        ex, ey = qx - px[:, None], qy - py[:, None]
        wgt = 1.0 / np.maximum(ex ** 2 + ey ** 2, 0.05)
    miss = wrap(np.arctan2(ey, ex) - th)
    cost = np.minimum(miss ** 2 / spread ** 2, 9.0).sum(axis=1)
    return np.column_stack([px, py]), cost


def chain_headings(costs: list[np.ndarray], positions: list[np.ndarray], moves: np.ndarray, headings: np.ndarray,
                   spread: float, cap: float = 25.0) -> np.ndarray:
    """The likeliest sequence of window start headings (index per window), by dynamic programming.

    Window k costs ``costs[k]`` at each heading and starts at ``positions[k]`` there; ``moves[k]`` is the
    dead-reckoned (dx, dy, dtheta) from window k's start to window k+1's, in window k's frame. Moving
    from heading i to heading j costs the squared misfit of position and heading against that move
    (its tolerance grows with the move's length and turn), capped at ``cap`` so that a stretch where dead
    reckoning fails (a slip, a rough floor) does not force a wrong chain. Each window alone cannot tell
    a heading when it sees two landmarks from nearly one place; its neighbours can.
    """
    c, s = np.cos(headings), np.sin(headings)
    total = costs[0].copy()
    back = []
    for k in range(len(costs) - 1):
        dx, dy, dth = moves[k]
        step = np.hypot(dx, dy)
        sp, sth = spread + 0.1 * step, 0.05 + 0.1 * abs(dth) + 0.02 * step
        px = positions[k][:, 0] + c * dx - s * dy          # where heading i puts window k+1's start
        py = positions[k][:, 1] + s * dx + c * dy
        dpos = ((positions[k + 1][None, :, 0] - px[:, None]) ** 2
                + (positions[k + 1][None, :, 1] - py[:, None]) ** 2) / sp ** 2
        dang = wrap(headings[None, :] - headings[:, None] - dth) ** 2 / sth ** 2
        trans = np.minimum(dpos + dang, cap)
        acc = total[:, None] + trans
        arg = np.argmin(acc, axis=0)
        back.append(arg)
        total = acc[arg, np.arange(len(headings))] + costs[k + 1]
    path = np.empty(len(costs), int)
    path[-1] = int(np.argmin(total))
    for k in range(len(costs) - 2, -1, -1):
        path[k] = back[k][path[k + 1]]
    return path


def window_start(log: Log, velocity: np.ndarray, n_poly: int, speed: float,
                 options: WindowOptions | None = None) -> WindowStart:
    """The global start of ``log`` given the nominal body ``velocity`` (T, 3) of each step.

    ``n_poly`` is the sensor polynomial's length, ``speed`` (m/s) the grid smoother's random walk (faster
    than the robot moves). See the module docstring for the steps.
    """
    o = options or WindowOptions()
    T, tp, dt = log.steps, log.pose_times, log.dt
    t0 = tp[0]
    knot_dt = o.knot_dt
    has_r, has_b = ~np.isnan(log.obs_reading), ~np.isnan(log.obs_bearing)
    both = has_r & has_b
    mode = "both" if both.sum() >= MIN_BOTH else ("range" if has_r.sum() >= has_b.sum() else "bearing")
    n_knots = int(np.ceil((tp[-1] - t0) / knot_dt)) + 1
    obs_knot = np.clip(np.round((log.obs_t - t0) / knot_dt).astype(int), 0, n_knots - 1)
    loc = None
    poly0 = np.zeros(n_poly)
    p_hyp, k_hyp = float("nan"), float("nan")
    if mode != "bearing":
        n_c = int(np.ceil((tp[-1] - t0) / (3 * knot_dt))) + 1
        c_knot = np.clip(np.round((log.obs_t - t0) / (3 * knot_dt)).astype(int), 0, n_c - 1)
        loc = locate(log, obs_knot, n_knots, knot_dt, c_knot, n_c, n_poly - 1,
                     o.cell if o.cell is not None else grid_cell(log), speed=speed)
        p_hyp, k_hyp = loc.hypothesis
        poly0 = loc.poly
        if p_hyp == 1.0:
            poly0 = np.zeros(n_poly)
            poly0[1] = k_hyp

    window = o.window_for(mode)
    ob = np.flatnonzero({"both": both, "range": has_r, "bearing": has_b}[mode])
    ob = ob[np.argsort(log.obs_step[ob], kind="stable")]
    step = log.obs_step[ob]
    lm = log.landmark_xy[log.landmark_index[ob]]
    win_of_step = np.floor((tp - t0) / window).astype(int)
    n_win = int(win_of_step[-1]) + 1
    win_start = np.searchsorted(win_of_step, np.arange(n_win))
    w_of = win_of_step[step]
    headings = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    spans = [(int(win_start[w]), int(win_start[w + 1]) if w + 1 < n_win else T) for w in range(n_win)]
    rels = [dead_reckon_steps(velocity[a:b], dt[a:b], np.zeros(3)) for a, b in spans]
    sels = [np.flatnonzero(w_of == w) for w in range(n_win)]
    d_max = 1.5 * np.ptp(log.landmark_xy, axis=0).max() + 3.0
    extent = float(np.ptp(log.landmark_xy, axis=0).max())
    if loc is not None and mode == "range":
        spread = max(0.15, 1.4826 * float(np.median(np.abs(loc.residual))) / max(abs(k_hyp), 1e-9))
    else:
        spread = max(0.15, 0.01 * extent)
    t_knot = t0 + knot_dt * np.arange(n_knots)
    track = dead_reckon_steps(velocity, dt, np.zeros(3))

    def chained(fits: dict, tolerance: float):
        """Window starts from per-heading fits, the headings chained across windows (:func:`chain_headings`)."""
        if not fits:
            return {}, 0.0
        ws = sorted(fits)
        a = np.array([spans[w][0] for w in ws])
        d = track[a[1:], :2] - track[a[:-1], :2]
        th = track[a[:-1], 2]
        moves = np.column_stack([np.cos(th) * d[:, 0] + np.sin(th) * d[:, 1],
                                 -np.sin(th) * d[:, 0] + np.cos(th) * d[:, 1],
                                 wrap(track[a[1:], 2] - th)])
        path = chain_headings([fits[w][1] for w in ws], [fits[w][0] for w in ws], moves, headings, tolerance)
        starts = {w: np.array([*fits[w][0][h], headings[h]]) for w, h in zip(ws, path)}
        return starts, float(sum(fits[w][1][h] for w, h in zip(ws, path)))

    def reading_distances(poly):
        """Each sighting's distance from its reading: through the hypothesis reading = k d**p itself when p is not 1
        (monotone, unlike a cubic the grid smoother fits to an apparent size: on an omni world one turned back at
        5.8 m and put the windows 5 m off), else through ``poly``'s monotone part."""
        z = log.obs_reading[ob]
        if p_hyp not in (1.0, 0.0) and np.isfinite(p_hyp) and k_hyp > 0 and np.all(z > 0):
            return np.clip((z / k_hyp) ** (1.0 / p_hyp), 0.05, d_max)
        return inverse_curve(poly, 0.05, d_max)(z)

    def place(poly):
        fits = {}
        dist = reading_distances(poly) if mode != "bearing" else None
        starts, total = {}, 0.0
        for w, ((a, _), rel, sel) in enumerate(zip(spans, rels, sels)):
            if len(sel) < 3:
                continue
            r = rel[step[sel] - a]
            if mode == "both":
                fits[w] = range_bearing_fits(lm[sel], dist[sel], log.obs_bearing[ob[sel]], r, headings)
            elif mode == "bearing":
                if len(np.unique(lm[sel], axis=0)) >= 2:
                    fits[w] = bearing_fits(lm[sel], log.obs_bearing[ob[sel]], r, headings, o.bearing_spread)
            else:
                # the heading shows only through motion: the window must move a few range errors
                if np.hypot(*rel[:, :2].T).max() < 3 * spread or len(np.unique(lm[sel], axis=0)) < 2:
                    continue
                guess = loc.mean[min(int(np.searchsorted(t_knot, tp[a])), n_knots - 1)]
                starts[w], c = window_pose_ranges(lm[sel], dist[sel], r, headings, guess, spread)
                total += c
        if mode == "range":
            return starts, total
        return chained(fits, 0.15 if mode == "both" else spread)

    def start_from(poly, starts):
        poses = np.empty((T + 1, 3))
        prev = None
        for w, (a, b) in enumerate(spans):
            begin = starts.get(w, prev if prev is not None else np.array([*log.landmark_xy.mean(axis=0), 0.0]))
            seg = dead_reckon_steps(velocity[a:b], dt[a:b], begin)
            poses[a:b + 1] = seg
            prev = seg[-1]
        sigma = float("nan")
        if mode != "bearing":
            res = log.obs_reading[ob] - np.polynomial.polynomial.polyval(np.hypot(*(lm - poses[step, :2]).T), poly)
            sigma = float(max(1.4826 * np.median(np.abs(res)), 1e-6))
        return WindowStart(poses, np.asarray(poly, float), sigma, (p_hyp, k_hyp),
                           loc.log_evidence if loc is not None else float("nan"), len(starts) / max(n_win, 1),
                           float(poly[1]) if mode != "bearing" else float("nan"))

    if p_hyp != 1.0:
        return start_from(poly0, place(poly0)[0])
    # a range line: its slope by how well the windows agree, the runners-up kept for the fit to try
    tried = sorted(((*place(poly0 * f)[::-1], f) for f in o.slope_factors), key=lambda t: t[0])
    ranked = [start_from(poly0 * f, starts) for _, starts, f in tried[:o.slope_starts]]
    return replace(ranked[0], alternatives=ranked[1:])
