"""Turn-rate aliasing: a segment's heading change is known from its end poses only modulo 2 pi.

Least squares cannot jump between the aliases w = (dtheta + 2 pi n) / duration of an action run
for a few seconds, so a wrong start for a rarely run action stays wrong. Here every action's
aliases are scored globally: the velocity table entry that would carry each of its segments from
its start pose to its end pose is solved for, each segment is dead-reckoned under it, and the
segment's own sightings decide which alias the robot really turned at.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

import factors
from casm_graph.graph.table import Layout
from casm_graph.io.log import Log, wrap
from casm_graph.models.model import Model

MAX_TURNS = 3
SPIN_TURN = 0.5     # rad a knot-to-knot segment turns beyond the model before it may belong to a spin


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


def _obs_costs(p0: np.ndarray, V: np.ndarray, n: int, dt: float, at: np.ndarray, lm: np.ndarray,
               reading: np.ndarray, bearing: np.ndarray, model: Model) -> np.ndarray:
    """``_obs_cost`` of one segment under every candidate velocity ``V`` (C, 3) at once.

    ``at`` are the sightings' steps from the segment start, ``lm`` their landmarks. Rolls the
    segment out as :func:`_roll` does and sums the same terms row by row, so each row equals
    ``_obs_cost(_roll(p0, V[c], n, dt), ...)`` exactly.
    """
    if not len(at):
        return np.zeros(len(V))
    th = p0[2] + (V[:, 2] * dt)[:, None] * np.arange(n + 1)
    c, s = np.cos(th)[:, :-1], np.sin(th)[:, :-1]
    zero = np.zeros((len(V), 1))
    x = p0[0] + np.concatenate([zero, np.cumsum((c * V[:, 0:1] - s * V[:, 1:2]) * dt, axis=1)], axis=1)
    y = p0[1] + np.concatenate([zero, np.cumsum((s * V[:, 0:1] + c * V[:, 1:2]) * dt, axis=1)], axis=1)
    rx, ry = lm[:, 0] - x[:, at], lm[:, 1] - y[:, at]
    d = np.hypot(rx, ry)
    r = (reading - model.reading(d)) / model.reading_sigma
    b = wrap(bearing - np.arctan2(ry, rx) + th[:, at]) / model.bearing_sigma
    # row-major before summing: x[:, at] is column-major, and numpy sums rows of that in another order
    r, b = np.ascontiguousarray(np.minimum(r * r, 25.0)), np.ascontiguousarray(np.minimum(b * b, 25.0))
    return np.nansum(r, axis=1) + np.nansum(b, axis=1)


def realias(log: Log, lay: Layout, model: Model, poses: np.ndarray) -> tuple[Model, np.ndarray, list[int]]:
    """Pick each action's best turn-rate alias; returns the model, the knot poses and the changed actions.

    Poses of segments whose action changed are re-drawn by dead reckoning with the closure error
    spread linearly; all other poses stay as they are.

    An action run in S segments has about 7 S candidate rates, each scored on all S segments; the
    scoring is vectorised over the candidates (one pass per segment), and the log's per-sighting
    indices are looked up once, so the work per segment is numpy's, not Python's.
    """
    segs = segments(lay)
    seg_act = lay.seg_action[[a for a, _ in segs]] if segs else np.array([], int)
    obs_step = log.obs_step
    step_sorted = np.argsort(obs_step, kind="stable")
    sorted_steps = obs_step[step_sorted]
    lm_all = log.landmark_xy[log.landmark_index]
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

        W = np.array(sorted(cands))
        Vw = np.zeros((len(W), 3))
        Vw[:, 2] = W
        J, rhs = [], []
        for k0, k1, _, n, dt, _ in info:
            J.append(factors.action.displacement(Vw, n, dt)[1][:, :2, :2])
            c, s = np.cos(poses[k0, 2]), np.sin(poses[k0, 2])
            ex, ey = poses[k1, 0] - poses[k0, 0], poses[k1, 1] - poses[k0, 1]
            rhs.append([c * ex + s * ey, -s * ex + c * ey])
        J = np.stack(J, axis=1)                 # (C, S, 2, 2)
        rhs = np.concatenate(rhs)
        V = np.empty((len(W), 3))
        for i, w in enumerate(W):               # the table entry's (vx, vy) that closes every segment under w
            vxy = np.linalg.lstsq(J[i].reshape(-1, 2), rhs, rcond=None)[0]
            V[i] = (vxy[0], vxy[1], w)
        total = np.zeros(len(W))
        for k0, k1, s0, n, dt, sel in info:
            total += _obs_costs(poses[k0], V, n, dt, obs_step[sel] - s0, lm_all[sel], log.obs_reading[sel],
                                log.obs_bearing[sel], model)
        scored = [((float(total[i]), V[i]), float(W[i])) for i in range(len(W))]
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


def spins(turn_residual: np.ndarray, min_turn: float = SPIN_TURN, span: np.ndarray | None = None,
          sighted: np.ndarray | None = None) -> list[tuple[int, int]]:
    """(first knot, last knot) of each spin: consecutive segments that each turn more than ``min_turn`` beyond the
    model and together a whole turn or more, which no local step undoes (each segment's wrapped residual would
    first have to grow). ``span`` (each segment's length) where segments differ: a segment then counts by its turn
    per unit length against ``min_turn`` per median segment, so that the short segment a knot at an action change
    cuts out of a spin does not break it. ``sighted`` (each knot: whether a sighting attaches to it): the path
    between two sighted knots with none between is held by the motion alone, so a whole turn beyond the model there
    is a spin however slowly it was wound (a start wound one over 13 s without sightings, 0.04 rad a step)."""
    turn = np.abs(turn_residual)
    big = turn > min_turn if span is None else turn / span > min_turn / np.median(span)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], big.astype(int), [0]])))
    runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]
    runs = [(a, b) for a, b in runs if abs(np.sum(turn_residual[a:b])) > np.pi]
    for a, b in unsighted(sighted) if sighted is not None else ():
        if abs(np.sum(turn_residual[a:b])) > np.pi and not any(a < d and c < b for c, d in runs):
            runs.append((a, b))
    return sorted(runs)


def unsighted(sighted: np.ndarray) -> list[tuple[int, int]]:
    """(sighted knot, next sighted knot) around each run of knots without a sighting (knots: ``sighted`` flags)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (~np.asarray(sighted, bool)).astype(int), [0]])))
    return [(max(int(a) - 1, 0), min(int(b), len(sighted) - 1)) for a, b in zip(edges[::2], edges[1::2])]


def unwind(poses: np.ndarray, turn_residual: np.ndarray, runs: list[tuple[int, int]]) -> np.ndarray:
    """Knot poses with each spin's headings re-drawn by the model's turns from its first knot, the closure error
    (the residuals' sum less its whole turns) spread linearly; positions and every other knot stay."""
    out = poses.copy()
    for a, b in runs:
        e = turn_residual[a:b]
        share = np.arange(1, b - a) / (b - a)
        out[a + 1:b, 2] = wrap(poses[a + 1:b, 2] - np.cumsum(e)[:-1] + share * wrap(np.sum(e)))
    return out


def unspun(problem, st, history, settle: Callable, span: np.ndarray | None = None) -> tuple:
    """``st`` (its least-squares ``history``) or, where its turn residuals hold a spin (:func:`spins`, ``span`` each
    segment's length: a whole turn wound into a few knots, or across a gap in the sightings, as a start can put one),
    the state unwound and settled by ``settle(state) -> (state, history)``, kept when it ends at the lower cost.
    Returns (state, history, iterations spent on the unwound state)."""
    turn = problem.motion_residual(st)[:, 2]
    runs = spins(turn, span=span, sighted=np.bincount(problem.lay.obs_knot, minlength=problem.lay.n_poses) > 0)
    if not runs:
        return st, history, 0
    tried, again = settle(replace(st, poses=unwind(st.poses, turn, runs)))
    return (tried, again, again.iterations) if again.cost[-1] < history.cost[-1] else (st, history, again.iterations)
