"""Turn-rate aliasing: a segment's heading change is known from its end poses only modulo 2 pi.

Least squares cannot jump between the aliases w = (dtheta + 2 pi n) / duration of an action run
for a few seconds, so a wrong start for a rarely run action stays wrong. Here every action's
aliases are scored globally: the velocity table entry that would carry each of its segments from
its start pose to its end pose is solved for, each segment is dead-reckoned under it, and the
segment's own sightings decide which alias the robot really turned at.
"""
from __future__ import annotations

import numpy as np

import factors

from .graph import Layout
from .log import Log, wrap
from .model import Model

MAX_TURNS = 3


def segments(lay: Layout) -> list[tuple[int, int]]:
    """(first knot, last knot) of each constant-action run of a layout."""
    change = np.flatnonzero(np.diff(lay.seg_action) != 0) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [lay.n_poses - 1]])
    return list(zip(starts.tolist(), ends.tolist()))


def _roll(p0: np.ndarray, v: np.ndarray, n: int, dt: float) -> np.ndarray:
    th = p0[2] + v[2] * dt * np.arange(n + 1)
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    x = p0[0] + np.concatenate([[0.0], np.cumsum((c * v[0] - s * v[1]) * dt)])
    y = p0[1] + np.concatenate([[0.0], np.cumsum((s * v[0] + c * v[1]) * dt)])
    return np.column_stack([x, y, th])


def _obs_cost(path: np.ndarray, first_step: int, sel: np.ndarray, log: Log, model: Model) -> float:
    if not len(sel):
        return 0.0
    p = path[log.obs_step[sel] - first_step]
    lm = log.landmark_xy[log.landmark_index[sel]]
    rel = lm - p[:, :2]
    d = np.hypot(rel[:, 0], rel[:, 1])
    r = (log.obs_reading[sel] - model.reading(d)) / model.reading_sigma
    b = wrap(log.obs_bearing[sel] - np.arctan2(rel[:, 1], rel[:, 0]) + p[:, 2]) / model.bearing_sigma
    return float(np.nansum(np.minimum(r * r, 25.0)) + np.nansum(np.minimum(b * b, 25.0)))


def realias(log: Log, lay: Layout, model: Model, poses: np.ndarray) -> tuple[Model, np.ndarray, list[int]]:
    """Pick each action's best turn-rate alias; returns the model, the knot poses and the changed actions.

    Poses of segments whose action changed are re-drawn by dead reckoning with the closure error
    spread linearly; all other poses stay as they are.
    """
    segs = segments(lay)
    seg_act = np.array([lay.seg_action[a] for a, _ in segs])
    obs_step = log.obs_step
    step_sorted = np.argsort(obs_step, kind="stable")
    sorted_steps = obs_step[step_sorted]
    vel = model.velocities.copy()
    poses = poses.copy()
    changed = []
    for a in np.unique(seg_act):
        mine = [segs[i] for i in np.flatnonzero(seg_act == a)]
        info = []
        for k0, k1 in mine:
            s0, s1 = int(lay.knots[k0]), int(lay.knots[k1])
            dt = float(np.mean(lay.seg_dt[k0:k1]))
            lo, hi = np.searchsorted(sorted_steps, [s0, s1 + 1])
            info.append((k0, k1, s0, s1 - s0, dt, step_sorted[lo:hi]))
        cands = {float(vel[a, 2])}
        for k0, k1, _, n, dt, _ in info:
            dth = wrap(poses[k1, 2] - poses[k0, 2])
            for m in range(-MAX_TURNS, MAX_TURNS + 1):
                cands.add(float((dth + 2 * np.pi * m) / (n * dt)))

        def score(w):
            rows, rhs = [], []
            for k0, k1, _, n, dt, _ in info:
                _, J = factors.action.displacement(np.array([[0.0, 0.0, w]]), n, dt)
                c, s = np.cos(poses[k0, 2]), np.sin(poses[k0, 2])
                ex, ey = poses[k1, 0] - poses[k0, 0], poses[k1, 1] - poses[k0, 1]
                rows.append(J[0, :2, :2])
                rhs.append([c * ex + s * ey, -s * ex + c * ey])
            vxy = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
            v = np.array([vxy[0], vxy[1], w])
            total = 0.0
            for k0, k1, s0, n, dt, sel in info:
                total += _obs_cost(_roll(poses[k0], v, n, dt), s0, sel, log, model)
            return total, v

        scored = [(score(w), w) for w in sorted(cands)]
        (best_cost, best_v), best_w = min(scored, key=lambda t: t[0][0])
        (cur_cost, _), _ = next(t for t in scored if t[1] == float(vel[a, 2]))
        if best_cost < cur_cost - 10.0 and abs(best_w - vel[a, 2]) > 0.05:
            vel[a] = best_v
            changed.append(int(a))
            for k0, k1, s0, n, dt, _ in info:
                path = _roll(poses[k0], best_v, n, dt)
                at = lay.knots[k0:k1 + 1] - s0
                frac = ((lay.knots[k0:k1 + 1] - s0) / n)[:, None]
                err = np.array([poses[k1, 0] - path[-1, 0], poses[k1, 1] - path[-1, 1],
                                wrap(poses[k1, 2] - path[-1, 2])])
                new = path[at] + frac * err
                new[:, 2] = wrap(new[:, 2])
                poses[k0:k1 + 1] = new
    return model.with_(velocities=vel), poses, changed
