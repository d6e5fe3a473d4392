"""The factor graph of one log: poses, action-table velocities and sensor coefficients as variables.

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

from .log import Log, nearest_index
from .model import Model

VELOCITY_PRIOR_SIGMA = 10.0      # weak priors keep never-run actions and the polynomial well posed
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
    act = np.searchsorted(model.action_ids, log.action)
    change = np.flatnonzero(np.diff(act) != 0) + 1
    knots = np.unique(np.concatenate([np.arange(0, T + 1, stride), change, [T]]))
    seg_steps = np.diff(knots)
    seg_action = act[knots[:-1]]
    cum = np.concatenate([[0.0], np.cumsum(log.dt)])
    seg_dt = (cum[knots[1:]] - cum[knots[:-1]]) / seg_steps
    obs_knot = nearest_index(knots.astype(float), log.obs_step.astype(float))
    return Layout(knots, seg_action, seg_steps, seg_dt, obs_knot, len(model.action_ids))


def build(log: Log, lay: Layout, model: Model, parts=("action", "reading", "bearing")) -> gtsam.NonlinearFactorGraph:
    """Factor graph of the log under ``model``'s noise levels (sigmas are fixed inside the factors)."""
    g = gtsam.NonlinearFactorGraph()
    if "action" in parts:
        kind = factors.REGISTRY["action"]
        base = np.asarray(model.motion_noise, float)
        for i in range(lay.n_poses - 1):
            k = int(lay.seg_steps[i])
            noise = gtsam.noiseModel.Diagonal.Sigmas(base * np.sqrt(k))
            g.add(kind.build(noise, (X(i), X(i + 1), V(int(lay.seg_action[i]))), k, float(lay.seg_dt[i])))
    lm = log.landmark_xy[log.landmark_index]
    if "reading" in parts:
        kind = factors.REGISTRY["reading"]
        noise = gtsam.noiseModel.Isotropic.Sigma(1, model.reading_sigma)
        for j in np.flatnonzero(~np.isnan(log.obs_reading)):
            g.add(kind.build(noise, (X(int(lay.obs_knot[j])), C(0)), lm[j], float(log.obs_reading[j])))
    if "bearing" in parts:
        kind = factors.REGISTRY["bearing"]
        noise = gtsam.noiseModel.Isotropic.Sigma(1, model.bearing_sigma)
        for j in np.flatnonzero(~np.isnan(log.obs_bearing)):
            g.add(kind.build(noise, (X(int(lay.obs_knot[j])),), lm[j], float(log.obs_bearing[j])))
    vprior = gtsam.noiseModel.Isotropic.Sigma(3, VELOCITY_PRIOR_SIGMA)
    for a in range(lay.n_actions):
        g.add(gtsam.PriorFactorVector(V(a), np.zeros(3), vprior))
    deg = len(model.reading_poly)
    g.add(gtsam.PriorFactorVector(C(0), np.zeros(deg), gtsam.noiseModel.Isotropic.Sigma(deg, POLY_PRIOR_SIGMA)))
    return g


def values(poses: np.ndarray, model: Model) -> gtsam.Values:
    """A Python-owned ``Values`` holding knot poses (K, 3), the velocity table and the polynomial."""
    v = gtsam.Values()
    for i, (x, y, th) in enumerate(poses):
        v.insert(X(i), gtsam.Pose2(x, y, th))
    for a, vel in enumerate(model.velocities):
        v.insert(V(a), np.asarray(vel, float))
    v.insert(C(0), np.asarray(model.reading_poly, float))
    return v


def ordering(lay: Layout) -> gtsam.Ordering:
    """Poses in time order, then the dense parameters (velocities, polynomial) last."""
    o = gtsam.Ordering()
    for i in range(lay.n_poses):
        o.push_back(X(i))
    for a in range(lay.n_actions):
        o.push_back(V(a))
    o.push_back(C(0))
    return o


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


def dead_reckon(log: Log, model: Model, start: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses from ``start`` integrating the table velocities with the per-step model."""
    v = model.velocity_of(log.action) * log.dt[:, None]
    th = start[2] + np.concatenate([[0.0], np.cumsum(v[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    x = start[0] + np.concatenate([[0.0], np.cumsum(c * v[:, 0] - s * v[:, 1])])
    y = start[1] + np.concatenate([[0.0], np.cumsum(s * v[:, 0] + c * v[:, 1])])
    return np.column_stack([x, y, th])
