"""The factor graph of one log: poses, action-table velocities and sensor coefficients as variables.

A :class:`Layout` says which command steps carry a pose variable ("knots"). The full graph has a
knot at every step; a coarse graph for initialisation keeps one every ``stride`` steps (and at
every action change), joins consecutive knots with one action factor over the steps between them,
and attaches each observation to its nearest knot.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
from gtsam.symbol_shorthand import C, M, V, X

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
    """The log as a GTSAM graph of ``CustomFactor``s (sigmas fixed inside the factors).

    This is the reference formulation, for GTSAM's own optimizers and marginals; :class:`Problem`
    linearises the same factors in one numpy pass for the hot path.
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


@dataclass
class State:
    """The variables of the graph as arrays: knot poses, velocity table, polynomial."""

    poses: np.ndarray        # (K, 3)
    velocities: np.ndarray   # (A, 3)
    poly: np.ndarray         # (D+1,)


@dataclass
class Rows:
    """Whitened residual rows and Jacobian blocks of every factor, grouped by channel."""

    action_e: np.ndarray     # (K-1, 3)
    action_J: list           # [Ha, Hb, Hv] each (K-1, 3, 3)
    reading_e: np.ndarray    # (Nr,)
    reading_J: list          # [Hp (Nr, 3), Hc (Nr, D+1)]
    bearing_e: np.ndarray    # (Nb,)
    bearing_J: np.ndarray    # (Nb, 3)
    prior_e: np.ndarray      # (3A + D + 1,) velocity and polynomial priors
    sighting_loss: float = 0.0   # sum of the sightings' Huber losses (times their inlier weights): their part of the cost
    anchor_e: np.ndarray = field(default_factory=lambda: np.zeros(0))   # (0,) or (1,) the first heading's hold


class Problem:
    """The graph of one log under fixed noise levels, evaluated and linearised in numpy.

    Holds the fixed data (layout, measurements, sigmas, and the sightings' inlier ``weight`` of a
    false-detection mixture when one is fitted); the variables travel as a :class:`State`. Sightings
    count through Huber's loss (:mod:`casm_graph.graph.robust`); ``huber=False`` makes them Gaussian,
    as the marginal likelihood of the uncertainty step models them. ``anchor`` holds the first pose's heading
    there (``ANCHOR_SIGMA``): without bearings every heading and body velocity may turn together, ranges and
    motion unchanged, and the anchor fixes that rotation where the start put it.
    """

    def __init__(self, log: Log, lay: Layout, model: Model, weight: np.ndarray | None = None, huber: bool = True,
                 anchor: float | None = None):
        self.log, self.lay = log, lay
        self.anchor = anchor
        self.motion_sigma = np.asarray(model.motion_noise, float)[None, :] * np.sqrt(lay.seg_steps)[:, None]
        lm = log.landmark_xy[log.landmark_index]
        r = ~np.isnan(log.obs_reading)
        b = ~np.isnan(log.obs_bearing)
        self.r_knot, self.r_lm, self.r_z = lay.obs_knot[r], lm[r], log.obs_reading[r]
        self.b_knot, self.b_lm, self.b_z = lay.obs_knot[b], lm[b], log.obs_bearing[b]
        self.reading_sigma, self.bearing_sigma = float(model.reading_sigma), float(model.bearing_sigma)
        self.n_poly, self.basis = len(model.reading_poly), model.reading_basis
        w = np.ones(len(log.obs_t)) if weight is None else np.asarray(weight, float)
        self.r_w, self.b_w = np.sqrt(w[r]), np.sqrt(w[b])
        self.counts = {"reading": float(np.sum(w[r])), "bearing": float(np.sum(w[b]))}
        self.k = robust.HUBER if huber else np.inf

    def rows(self, st: State, jacobians: bool = True) -> Rows:
        lay = self.lay
        P = st.poses
        e, J = factors.action.error(P[:-1], P[1:], st.velocities[lay.seg_action], lay.seg_steps, lay.seg_dt)
        w = 1.0 / self.motion_sigma
        ae, aJ = e * w, [j * w[:, :, None] for j in J]
        e, J = factors.reading.error(P[self.r_knot], st.poly[None], self.r_lm, self.r_z, self.basis)
        re, rJ = e[:, 0] / self.reading_sigma, [J[0][:, 0] / self.reading_sigma, J[1][:, 0] / self.reading_sigma]
        loss = float(np.sum(self.r_w ** 2 * robust.huber_loss(re, self.k)))
        w = robust.huber(re, self.k) * self.r_w       # a wild sighting pulls like one HUBER sigmas off, no more
        re, rJ = re * w, [rJ[0] * w[:, None], rJ[1] * w[:, None]]
        e, J = factors.bearing.error(P[self.b_knot], self.b_lm, self.b_z)
        be, bJ = e[:, 0] / self.bearing_sigma, J[0][:, 0] / self.bearing_sigma
        loss += float(np.sum(self.b_w ** 2 * robust.huber_loss(be, self.k)))
        w = robust.huber(be, self.k) * self.b_w
        be, bJ = be * w, bJ * w[:, None]
        pe = np.concatenate([st.velocities.ravel() / VELOCITY_PRIOR_SIGMA, st.poly / POLY_PRIOR_SIGMA])
        he = np.zeros(0) if self.anchor is None else np.array([wrap(P[0, 2] - self.anchor) / ANCHOR_SIGMA])
        return Rows(ae, aJ, re, rJ, be, bJ, pe, loss, he)

    def cost(self, st: State) -> float:
        """GTSAM's error: half the sum of squared whitened residuals, sightings through Huber's loss."""
        r = self.rows(st, jacobians=False)
        return 0.5 * float(np.sum(r.action_e ** 2) + np.sum(r.prior_e ** 2) + np.sum(r.anchor_e ** 2)) + r.sighting_loss

    def linearize(self, st: State, poses_only: bool = False) -> gtsam.GaussianFactorGraph:
        """Gauss-Newton system at ``st``: one factor per action segment and per knot with sightings.

        ``poses_only`` holds the table and polynomial fixed (their columns and priors left out).
        """
        r = self.rows(st)
        lay, unit3 = self.lay, gtsam.noiseModel.Unit.Create(3)
        g = gtsam.GaussianFactorGraph()
        Ha, Hb, Hv = r.action_J
        for i in range(lay.n_poses - 1):
            if poses_only:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], -r.action_e[i], unit3)
            else:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], V(int(lay.seg_action[i])), Hv[i], -r.action_e[i], unit3)
        D = self.n_poly
        hk, hJ = anchor_rows(r.anchor_e)
        knot = np.concatenate([self.r_knot, self.b_knot, hk])
        Jp = np.concatenate([r.reading_J[0], r.bearing_J, hJ])
        Jc = np.concatenate([r.reading_J[1], np.zeros((len(self.b_knot) + len(hk), D))])
        e = np.concatenate([r.reading_e, r.bearing_e, r.anchor_e])
        order = np.argsort(knot, kind="stable")
        add_sightings(g, knot[order], Jp[order], Jc[order], e[order], poses_only)
        if poses_only:
            return g
        eye3 = np.eye(3) / VELOCITY_PRIOR_SIGMA
        for a in range(lay.n_actions):
            g.add(V(a), eye3, -r.prior_e[3 * a:3 * a + 3], unit3)
        g.add(C(0), np.eye(D) / POLY_PRIOR_SIGMA, -r.prior_e[3 * lay.n_actions:], gtsam.noiseModel.Unit.Create(D))
        return g

    def retract(self, st: State, delta: gtsam.VectorValues) -> State:
        """Apply a tangent step: poses move in their own body frame (Pose2 expmap to first order)."""
        poses = retract_poses(st.poses, delta)
        if not delta.exists(C(0)):
            return State(poses, st.velocities, st.poly)
        vel = st.velocities + np.array([delta.at(V(a)) for a in range(self.lay.n_actions)])
        return State(poses, vel, st.poly + np.asarray(delta.at(C(0))))

    def keys_dims(self) -> list[tuple[int, int]]:
        return ([(X(i), 3) for i in range(self.lay.n_poses)] + [(V(a), 3) for a in range(self.lay.n_actions)]
                + [(C(0), self.n_poly)])

    def _order(self) -> np.ndarray:
        if getattr(self, "_elimination", None) is None:
            self._elimination = elimination_order(self.lay.seg_action, self.lay.n_poses, self.lay.n_actions + 1)
        return self._elimination

    def ordering(self, poses_only: bool = False) -> gtsam.Ordering:
        """Elimination order for GTSAM's solve (:func:`elimination_order`)."""
        K, A = self.lay.n_poses, self.lay.n_actions
        order = self._order()
        if poses_only:
            order = order[order < K]
        return gtsam.Ordering([X(int(i)) if i < K else V(int(i - K)) if i < K + A else C(0) for i in order])

    def column_order(self) -> np.ndarray:
        """The same order over the columns of :meth:`jacobian` (for the noise step's sparse LU)."""
        K, A, D = self.lay.n_poses, self.lay.n_actions, self.n_poly
        order = self._order()
        cols = [(3 * order[order < K, None] + np.arange(3)).ravel()]
        cols += [3 * i + np.arange(3) if i < K + A else 3 * K + 3 * A + np.arange(D) for i in order[order >= K]]
        return np.concatenate(cols)

    def jacobian(self, st: State):
        """Whitened sparse Jacobian (rows: action x/y/theta interleaved, reading, bearing, priors) and residual."""
        r = self.rows(st)
        K, A, D = self.lay.n_poses, self.lay.n_actions, self.n_poly
        n_act, n_r, n_b = 3 * (K - 1), len(r.reading_e), len(r.bearing_e)
        rows, cols, vals = [], [], []

        def block(row0, J, col0):
            n, m, d = J.shape
            rr = row0[:, None, None] + np.arange(m)[None, :, None]
            cc = col0[:, None, None] + np.arange(d)[None, None, :]
            rows.append(np.broadcast_to(rr, J.shape).ravel())
            cols.append(np.broadcast_to(cc, J.shape).ravel())
            vals.append(J.ravel())

        seg = np.arange(K - 1)
        Ha, Hb, Hv = r.action_J
        block(3 * seg, Ha, 3 * seg)
        block(3 * seg, Hb, 3 * (seg + 1))
        block(3 * seg, Hv, 3 * K + 3 * self.lay.seg_action)
        block(n_act + np.arange(n_r), r.reading_J[0][:, None, :], 3 * self.r_knot)
        block(n_act + np.arange(n_r), r.reading_J[1][:, None, :], np.full(n_r, 3 * K + 3 * A))
        block(n_act + n_r + np.arange(n_b), r.bearing_J[:, None, :], 3 * self.b_knot)
        n_p, n_h = 3 * A + D, len(r.anchor_e)
        prior = np.concatenate([np.full(3 * A, 1 / VELOCITY_PRIOR_SIGMA), np.full(D, 1 / POLY_PRIOR_SIGMA)])
        rows.append(n_act + n_r + n_b + np.arange(n_p))
        cols.append(3 * K + np.arange(n_p))
        vals.append(prior)
        hk, hJ = anchor_rows(r.anchor_e)
        block(n_act + n_r + n_b + n_p + np.arange(n_h), hJ[:, None, :], 3 * hk)
        shape = (n_act + n_r + n_b + n_p + n_h, 3 * K + n_p)
        A_ = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape)
        e = np.concatenate([r.action_e.ravel(), r.reading_e, r.bearing_e, r.prior_e, r.anchor_e])
        groups = {"forward": np.arange(0, n_act, 3), "lateral": np.arange(1, n_act, 3),
                  "turn": np.arange(2, n_act, 3), "reading": n_act + np.arange(n_r),
                  "bearing": n_act + n_r + np.arange(n_b)}
        return A_, e, groups


def anchor_rows(anchor_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The heading anchor's whitened rows as sightings of pose 0: their knots (0) and pose Jacobians (on theta)."""
    J = np.zeros((len(anchor_e), 3))
    J[:, 2] = 1.0 / ANCHOR_SIGMA
    return np.zeros(len(anchor_e), int), J


def heading_anchor(log: Log, poses: np.ndarray) -> float | None:
    """The first heading a graph of ``log`` holds (``poses`` its start): on a log without bearings only, where
    turning every heading and body velocity together changes nothing the log measures."""
    return None if "bearing" in log.channels else float(poses[0, 2])


def state(poses: np.ndarray, model: Model) -> State:
    return State(np.asarray(poses, float).copy(), np.asarray(model.velocities, float).copy(),
                 np.asarray(model.reading_poly, float).copy())


def values(poses: np.ndarray, model: Model) -> gtsam.Values:
    """A Python-owned ``Values`` holding knot poses (K, 3), the velocity table and the polynomial."""
    v = gtsam.Values()
    for i, (x, y, th) in enumerate(poses):
        v.insert(X(i), gtsam.Pose2(x, y, th))
    for a, vel in enumerate(model.velocities):
        v.insert(V(a), np.asarray(vel, float))
    v.insert(C(0), np.asarray(model.reading_poly, float))
    return v


def elimination_order(seg_action: np.ndarray | None, n_poses: int, n_params: int) -> np.ndarray:
    """Elimination order of a pose chain and its parameter blocks, found in time linear in the chain's length.

    Variables are numbered 0..K-1 (poses), then K.. (parameter blocks); ``seg_action[k]`` is the
    parameter block of the segment from pose k to k+1 (None: one block shared by every segment), and
    the last block (the polynomial) is seen from every pose. GTSAM's default (COLAMD) and SuperLU's
    minimum-degree orderings take time quadratic in the number of poses on these graphs (issue 25:
    22 s per solve on a 2-hour log). Here the poses inside each constant-action run go first, in
    time order: eliminating them involves only the run's two end poses, its own block and the
    polynomial. The run ends and the parameter blocks, a graph the size of the number of runs,
    follow in COLAMD's order for that graph.
    """
    K = n_poses
    if seg_action is None or n_poses < 3:
        return np.arange(K + n_params)
    ends = np.ones(K, bool)
    ends[1:-1] = seg_action[1:] != seg_action[:-1]
    inner, b = np.flatnonzero(~ends), np.flatnonzero(ends)
    sg = gtsam.SymbolicFactorGraph()
    for j in range(len(b) - 1):
        sg.push_factor(int(b[j]), int(b[j + 1]), K + int(seg_action[b[j]]), K + n_params - 1)
    o = gtsam.Ordering.ColamdSymbolicFactorGraph(sg)
    rest = np.array([o.at(i) for i in range(o.size())], dtype=np.int64)
    unused = np.setdiff1d(K + np.arange(n_params), rest)          # blocks of no segment (never-run actions)
    return np.concatenate([inner, rest, unused])


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


def add_sightings(g: gtsam.GaussianFactorGraph, knot, Jp, Jc, e, poses_only: bool, Jm=None) -> None:
    """Linearised reading and bearing rows as one Jacobian factor per knot (rows sorted by knot); ``Jm``, when
    given, their columns on the model vector M(0) (a continuous log's command map and effect parameters)."""
    cuts = np.flatnonzero(np.diff(knot)) + 1
    for s0, s1 in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(knot)]])):
        noise = gtsam.noiseModel.Unit.Create(int(s1 - s0))
        if poses_only:
            g.add(X(int(knot[s0])), Jp[s0:s1], -e[s0:s1], noise)
        elif Jm is None:
            g.add(X(int(knot[s0])), Jp[s0:s1], C(0), Jc[s0:s1], -e[s0:s1], noise)
        else:
            g.add(X(int(knot[s0])), Jp[s0:s1], C(0), Jc[s0:s1], M(0), Jm[s0:s1], -e[s0:s1], noise)


def dead_reckon(log: Log, model: Model, start: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses from ``start`` integrating the table velocities with the per-step model."""
    return integrate(start, model.velocity_of(log.action) * log.dt[:, None])
