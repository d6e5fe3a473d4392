"""The layout of an action-table log's graph, its GTSAM reference formulation, and pose helpers.

A :class:`Layout` says which command steps carry a pose variable ("knots"). The full graph has a
knot at every step; a coarse graph for initialisation keeps one every ``stride`` steps (and at
every action change), joins consecutive knots with one action factor over the steps between them,
and attaches each observation to its nearest knot.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import C, V, X

import factors
from casm_graph.graph import robust
from casm_graph.io.log import Log, nearest_index, wrap
from casm_graph.models.model import Model

ANCHOR_SIGMA = 1e-3             # rad: the first heading's hold on a log without bearings (a gauge, not information)
VELOCITY_PRIOR_SIGMA = 1.0       # m/s, rad/s: keeps never-run actions posed and a wrong basin from running off (BENCHMARKS.md)
POLY_PRIOR_SIGMA = 1e4


@dataclass(frozen=True)
class Layout:
    """Which steps carry poses and how factors attach to them."""

    knots: np.ndarray        # (K,) pose-step index of each pose variable
    seg_action: np.ndarray   # (K-1,) row in model.action_ids of the action run between knots
    seg_steps: np.ndarray    # (K-1,) command steps between consecutive knots
    seg_dt: np.ndarray       # (K-1,) mean step length between consecutive knots
    obs_knot: np.ndarray     # (N,) knot each observation attaches to
    n_actions: int

    @property
    def n_poses(self) -> int:
        return len(self.knots)


def layout(log: Log, model: Model, stride: int = 1) -> Layout:
    """Knots every ``stride`` steps and at every action change (always at the first and last pose)."""
    T = log.steps
    act = model.action.rows_of(log.action)
    change = np.flatnonzero(np.diff(act) != 0) + 1
    knots = np.unique(np.concatenate([np.arange(0, T + 1, stride), change, [T]]))
    seg_steps = np.diff(knots)
    seg_action = act[knots[:-1]]
    seg_dt = np.add.reduceat(log.dt, knots[:-1]) / seg_steps
    obs_knot = nearest_index(knots.astype(float), log.obs_step.astype(float))
    return Layout(knots, seg_action, seg_steps, seg_dt, obs_knot, len(model.action_ids))


def build(log: Log, lay: Layout, model: Model, parts=("action", "reading", "bearing")) -> gtsam.NonlinearFactorGraph:
    """The log as a GTSAM graph of ``CustomFactor``s (sigmas fixed inside the factors).

    This is the reference formulation, for GTSAM's own optimizers and marginals;
    :class:`casm_graph.graph.problem.Problem` linearises the same factors in one numpy pass for the hot path.
    """
    g = gtsam.NonlinearFactorGraph()
    if "action" in parts:
        kind = factors.REGISTRY["action"]
        base = np.asarray(model.motion_noise, float)
        for i in range(lay.n_poses - 1):
            k = int(lay.seg_steps[i])
            noise = gtsam.noiseModel.Diagonal.Sigmas(base * np.sqrt(k))
            g.add(kind.build(noise, (X(i), X(i + 1), V(int(lay.seg_action[i]))), k, float(lay.seg_dt[i])))
    lm = log.landmark_xy[log.landmark_index]
    huber = gtsam.noiseModel.mEstimator.Huber.Create(robust.HUBER)
    if "reading" in parts:
        kind = factors.REGISTRY["reading"]
        noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(1, model.reading_sigma))
        for j in np.flatnonzero(~np.isnan(log.obs_reading)):
            g.add(kind.build(noise, (X(int(lay.obs_knot[j])), C(0)), lm[j], float(log.obs_reading[j])))
    if "bearing" in parts:
        kind = factors.REGISTRY["bearing"]
        noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(1, model.bearing_sigma))
        for j in np.flatnonzero(~np.isnan(log.obs_bearing)):
            g.add(kind.build(noise, (X(int(lay.obs_knot[j])),), lm[j], float(log.obs_bearing[j])))
    vprior = gtsam.noiseModel.Isotropic.Sigma(3, VELOCITY_PRIOR_SIGMA)
    for a in range(lay.n_actions):
        g.add(gtsam.PriorFactorVector(V(a), np.zeros(3), vprior))
    deg = len(model.reading_poly)
    g.add(gtsam.PriorFactorVector(C(0), np.zeros(deg), gtsam.noiseModel.Isotropic.Sigma(deg, POLY_PRIOR_SIGMA)))
    return g


def anchor_rows(anchor_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The heading anchor's whitened rows as sightings of pose 0: their knots (0) and pose Jacobians (on theta)."""
    J = np.zeros((len(anchor_e), 3))
    J[:, 2] = 1.0 / ANCHOR_SIGMA
    return np.zeros(len(anchor_e), int), J


def heading_anchor(log: Log, poses: np.ndarray) -> float | None:
    """The first heading a graph of ``log`` holds (``poses`` its start): on a log without bearings only, where
    turning every heading and body velocity together changes nothing the log measures."""
    return None if "bearing" in log.channels else float(poses[0, 2])


def values(poses: np.ndarray, model: Model) -> gtsam.Values:
    """A Python-owned ``Values`` holding knot poses (K, 3), the velocity table and the polynomial."""
    v = gtsam.Values()
    for i, (x, y, th) in enumerate(poses):
        v.insert(X(i), gtsam.Pose2(x, y, th))
    for a, vel in enumerate(model.velocities):
        v.insert(V(a), np.asarray(vel, float))
    v.insert(C(0), np.asarray(model.reading_poly, float))
    return v


def poses_of(vals: gtsam.Values, n: int) -> np.ndarray:
    """(n, 3) knot poses from ``vals``."""
    out = np.empty((n, 3))
    for i in range(n):
        p = vals.atPose2(X(i))
        out[i] = (p.x(), p.y(), p.theta())
    return out


def parameters_of(vals: gtsam.Values, model: Model) -> Model:
    """``model`` with the velocities and polynomial read back from ``vals``."""
    vel = np.array([vals.atVector(V(a)) for a in range(len(model.action_ids))])
    return model.with_(velocities=vel, reading_poly=np.array(vals.atVector(C(0))))


def integrate(start: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses from ``start`` adding the body-frame displacements ``steps`` (T, 3), heading held over each step."""
    th = start[2] + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    x = start[0] + np.concatenate([[0.0], np.cumsum(c * steps[:, 0] - s * steps[:, 1])])
    y = start[1] + np.concatenate([[0.0], np.cumsum(s * steps[:, 0] + c * steps[:, 1])])
    return np.column_stack([x, y, th])


def fill_between(knots: np.ndarray, knot_poses: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses: each knot-to-knot stretch integrated from its knot, its closure error spread linearly."""
    out = np.empty((len(steps) + 1, 3))
    for i in range(len(knots) - 1):
        a, b = int(knots[i]), int(knots[i + 1])
        seg = integrate(knot_poses[i], steps[a:b])
        err = np.array([knot_poses[i + 1, 0] - seg[-1, 0], knot_poses[i + 1, 1] - seg[-1, 1],
                        wrap(knot_poses[i + 1, 2] - seg[-1, 2])])
        out[a:b + 1] = seg + np.linspace(0.0, 1.0, b - a + 1)[:, None] * err
    out[:, 2] = wrap(out[:, 2])
    return out


def retract_poses(poses: np.ndarray, delta) -> np.ndarray:
    """Poses moved by their tangent steps (``X(i)`` of a VectorValues, or an (n, 3) array) in their own
    body frame (Pose2 expmap to first order)."""
    d = np.array([delta.at(X(i)) for i in range(len(poses))]) if isinstance(delta, gtsam.VectorValues) else delta
    th = poses[:, 2]
    c, s = np.cos(th), np.sin(th)
    return np.column_stack([poses[:, 0] + c * d[:, 0] - s * d[:, 1], poses[:, 1] + s * d[:, 0] + c * d[:, 1],
                            wrap(th + d[:, 2])])


def dead_reckon(log: Log, model: Model, start: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses from ``start`` integrating the table velocities with the per-step model."""
    return integrate(start, model.velocity_of(log.action) * log.dt[:, None])
