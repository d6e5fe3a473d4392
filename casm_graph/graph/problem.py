"""The factor graph of one action-table log: poses, velocity table, sensor curve and any effects' parameters.

One class serves every graph of such a log: the calibration's coarse graph (a pose every ``stride``
steps, :func:`casm_graph.graph.table.layout`) and full graph, graph-em's E-step, the effect fits, the
diagnosis and the uncertainty step. The parameters (the table's rows, the curve's coefficients, the
least-squares parameters of the effects) travel as one vector, the dense arm of an arrow whose shaft is
the pose chain; each row's Jacobian touches a few of its columns. Without effects the factors are the
analytic ones of :mod:`factors`; an effect's hooks add the chained derivatives of
:mod:`factors.effect_motion` and :mod:`factors.effect_sighting`. Noise-only effects (range-dependent
noise, false detections) set per-observation scales and inlier weights that the noise step
re-estimates, as for the sigmas. Sightings count through Huber's loss unless ``huber=False``
(the effect fits and the marginal likelihood model them as Gaussian).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
from gtsam.symbol_shorthand import T, X

import factors
from casm_graph.graph import chain, robust
from casm_graph.graph import table as G
from casm_graph.graph.augmented import (motion_function, parameter_prior, parameter_slices, reading_scale,
                                        sensor_function, theta_from_model)
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects import Effect
from casm_graph.models.effects.false_detections import mixture_terms, reading_span
from casm_graph.models.model import Model

THETA = T(0)                      # the parameter vector's key in GTSAM graphs: table rows, curve, effects


@dataclass
class State:
    """Variables: the poses of the layout's knots, the table, the polynomial, and the effects' parameters."""

    poses: np.ndarray                # (K, 3)
    velocities: np.ndarray           # (A, 3)
    poly: np.ndarray                 # (D,)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))   # every effect parameter, noise-only ones too


@dataclass
class Rows:
    """Whitened residuals and Jacobian blocks of every factor, grouped by channel (parameter blocks None when
    not asked for: a poses-only solve of a graph with one table row per step never forms them)."""

    action_e: np.ndarray             # (K-1, 3)
    action_J: list                   # [Ha (K-1,3,3), Hb (K-1,3,3), Htheta (K-1,3,n) or None]
    reading_e: np.ndarray            # (Nr,)
    reading_J: list                  # [Hp (Nr,3), Htheta (Nr,n) or None]
    bearing_e: np.ndarray            # (Nb,)
    bearing_J: np.ndarray            # (Nb, 3)
    bearing_Jt: np.ndarray | None    # (Nb, n)
    prior_e: np.ndarray              # (n,)
    prior_J: np.ndarray              # (n,) diagonal
    sighting_loss: float = 0.0       # the sightings' part of the cost (Huber's loss times their inlier weights)
    anchor_e: np.ndarray = field(default_factory=lambda: np.zeros(0))   # (0,) or (1,) the first heading's hold
    standoff: tuple = (np.zeros(0, int), np.zeros(0), np.zeros((0, 3)))  # (knot, e, pose Jacobian) of the standoff


class Problem:
    """One log under fixed noise levels, with its effects; evaluated and linearised in numpy.

    ``lay`` is the pose layout (a pose every step when omitted; effects need that). ``weight`` gives
    each sighting's inlier weight (a false-detection mixture's), ``obs_mask`` hides sightings (held-out
    folds, gated outliers). ``anchor`` holds the first pose's heading there (``graph.table.ANCHOR_SIGMA``):
    without bearings every heading and body velocity may turn together, ranges and motion unchanged.
    """

    def __init__(self, log: Log, model: Model, effects: list[Effect] = (), *, lay: G.Layout | None = None,
                 theta: np.ndarray | None = None, obs_mask: np.ndarray | None = None,
                 weight: np.ndarray | None = None, huber: bool = True, anchor: float | None = None):
        self.log, self.model, self.effects = log, model, list(effects)
        self.anchor = anchor
        self.lay = lay = G.layout(log, model, stride=1) if lay is None else lay
        if self.effects and np.any(lay.seg_steps != 1):
            raise ValueError("effects act step by step: their graph needs a pose at every step")
        self.k = robust.HUBER if huber else np.inf
        self.slices = parameter_slices(self.effects)
        ls = np.concatenate([np.arange(s.start, s.stop) for e, s in zip(self.effects, self.slices)
                             if not e.noise_only] + [np.zeros(0, int)]).astype(int)
        self.ls_index = ls                                   # effect parameters that least squares moves
        self.A, self.D = lay.n_actions, len(model.reading_poly)
        self.n_theta = 3 * self.A + self.D + len(ls)
        self.basis = model.reading_basis
        self.motion_effects = [(e, s) for e, s in zip(self.effects, self.slices) if e.channel == "motion"]
        self.sensor_effects = [(e, s) for e, s in zip(self.effects, self.slices) if e.channel == "sensor"]
        # motion context (one row per segment; a step each when effects are present)
        act = lay.seg_action
        change = np.concatenate([[True], act[1:] != act[:-1]])
        start_idx = np.maximum.accumulate(np.where(change, np.arange(len(act)), 0))
        self.prev_row = np.where(start_idx > 0, act[np.maximum(start_idx - 1, 0)], act)
        t_rel = log.t[lay.knots[:-1]] - log.t[0]
        self.m_ctx = {"t": t_rel, "since": t_rel - t_rel[start_idx], "dt": lay.seg_dt * lay.seg_steps}
        self.motion_sigma = np.asarray(model.motion_noise, float)[None, :] * np.sqrt(lay.seg_steps)[:, None]
        # observations
        n_obs = len(log.obs_t)
        self.obs_mask = np.ones(n_obs, bool) if obs_mask is None else np.asarray(obs_mask, bool)
        self.obs_knot = lay.obs_knot
        self.obs_lm = log.landmark_index
        self.obs_lmxy = log.landmark_xy[self.obs_lm]
        self.pan = log.camera_pan
        self.r_idx = np.flatnonzero(np.isfinite(log.obs_reading) & self.obs_mask)
        self.b_idx = np.flatnonzero(np.isfinite(log.obs_bearing) & self.obs_mask)
        self.r_knot, self.b_knot = self.obs_knot[self.r_idx], self.obs_knot[self.b_idx]
        self.r_lm, self.b_lm = self.obs_lmxy[self.r_idx], self.obs_lmxy[self.b_idx]
        self.s_idx = np.union1d(self.r_idx, self.b_idx)      # every sighting in the graph: its pose keeps off the landmark
        # a coarse layout's sighting lies some steps from its knot: the knot's pose is carried there by the
        # model's velocity of the action between (one action per segment: knots at every change), held for the
        # problem's life like the noise levels, so that sightings inform the table only through the poses
        shift = log.obs_step - lay.knots[lay.obs_knot]
        self.obs_shift = shift if np.any(shift) else None
        if self.obs_shift is not None:
            seg = np.clip(np.where(shift >= 0, lay.obs_knot, lay.obs_knot - 1), 0, lay.n_poses - 2)
            sign = np.where(shift < 0, -1.0, 1.0)
            v = np.asarray(model.velocities, float)[lay.seg_action[seg]] * sign[:, None]
            self.obs_carry = factors.action.displacement(v, np.abs(shift), lay.seg_dt[seg])[0]
        self.reading_sigma, self.bearing_sigma = float(model.reading_sigma), float(model.bearing_sigma)
        self.reading_span = reading_span(log.obs_reading)
        self.r_scale = np.ones(n_obs)
        self.weight = np.ones(n_obs) if weight is None else np.asarray(weight, float).copy()
        th0 = theta if theta is not None else theta_from_model(self.effects, model)
        self.theta_noise = np.asarray(th0, float).copy()
        self.prior_mean, self.prior_sigma = parameter_prior(self.effects, self.slices)

    @property
    def counts(self) -> dict[str, float]:
        """Each sighting channel's row count, its sightings' inlier weights summed."""
        return {"reading": float(np.sum(self.weight[self.r_idx])), "bearing": float(np.sum(self.weight[self.b_idx]))}

    # ------------------------------------------------------------------ state
    def state(self, poses: np.ndarray, model: Model, theta: np.ndarray | None = None) -> State:
        """The variables at ``poses`` and ``model``'s table and curve; the effects' at ``theta`` (the problem's own
        when None)."""
        th = self.theta_noise.copy() if theta is None else np.asarray(theta, float).copy()
        return State(np.asarray(poses, float).copy(), np.asarray(model.velocities, float).copy(),
                     np.asarray(model.reading_poly, float).copy(), th)

    def pack(self, st: State) -> np.ndarray:
        return np.concatenate([st.velocities.ravel(), st.poly, st.theta[self.ls_index]])

    # ------------------------------------------------------------- evaluation
    def step_velocity(self, st: State) -> np.ndarray:
        """(S, 3) velocity each segment runs under the table and the motion effects."""
        return factors.effect_motion.velocity(self._motion_fn(st), st.velocities[self.lay.seg_action],
                                              st.velocities[self.prev_row], st.poses[:-1])

    def _motion_fn(self, st: State):
        return motion_function(self.motion_effects, self.m_ctx, st.theta)

    def sensor_context(self, st: State) -> dict:
        """Context of every observation under ``st`` (velocity from the previous step)."""
        v = self.step_velocity(st)
        step = np.clip(self.log.obs_step - 1, 0, len(v) - 1)
        return {"t": self.log.obs_t - self.log.t[0], "landmark": self.obs_lm, "pan": self.pan,
                "velocity": v[step]}

    def _sensor_fn(self, ctx):
        return sensor_function(self.sensor_effects, ctx, self.obs_lmxy, self.basis)

    def predictions(self, st: State) -> dict:
        """Predicted reading, bearing and distance of every observation (masked or not)."""
        fn = self._sensor_fn(self.sensor_context(st))
        idx = np.arange(len(self.log.obs_t))
        pred, bearing, d = fn(st.theta, st.poses[self.obs_knot], st.poly, idx)
        return {"reading": pred, "bearing": wrap(bearing), "distance": d}

    def _motion_rows(self, st: State, jacobians: bool, parameters: bool):
        lay, P = self.lay, st.poses
        S = lay.n_poses - 1
        w = 1.0 / self.motion_sigma
        if self.motion_effects:
            e, (Ha, Hb, _), dv = factors.effect_motion.error(
                self._motion_fn(st), P, st.velocities, lay.seg_action, self.prev_row, self.log.dt,
                st.theta, self.ls_index, [s for _, s in self.motion_effects])
            own, prev, Ha = dv["own"], dv["prev"], Ha + dv["pose"]
            d_theta = dv["theta"]
        else:
            e, (Ha, Hb, own) = factors.action.error(P[:-1], P[1:], st.velocities[lay.seg_action], lay.seg_steps,
                                                    lay.seg_dt)
            prev, d_theta = None, None
        ae = e * w
        if not jacobians:
            return ae, [None, None, None]
        Ht = None
        if parameters:
            Ht = np.zeros((S, 3, self.n_theta))
            rows3 = np.arange(S)
            own = own * w[:, :, None]
            prev = None if prev is None else prev * w[:, :, None]
            for c in range(3):             # one row per step in each statement: no repeated index, no add.at
                Ht[rows3, :, 3 * lay.seg_action + c] += own[:, :, c]
                if prev is not None:
                    Ht[rows3, :, 3 * self.prev_row + c] += prev[:, :, c]
            if d_theta is not None:
                Ht[:, :, 3 * self.A + self.D:] = d_theta * w[:, :, None]
        return ae, [Ha * w[:, :, None], Hb * w[:, :, None], Ht]

    def sighting_poses(self, st: State, idx: np.ndarray):
        """Poses of sightings ``idx``: their knots' (a pose every step), or on a coarse layout each knot's pose
        carried over the steps to the sighting (``obs_carry``); with the tangent derivative (n, 3, 3) of each
        with respect to the knot's pose (None at a pose every step)."""
        p = st.poses[self.obs_knot[idx]]
        if self.obs_shift is None:
            return p, None
        d = self.obs_carry[idx]
        out = G.retract_poses(p, d)                       # the displacement taken in the knot's body frame
        cd, sd = np.cos(d[:, 2]), np.sin(d[:, 2])
        back = np.zeros((len(p), 3, 3))                   # d(new tangent) / d(displacement): R(-dtheta), 1
        back[:, 0, 0], back[:, 0, 1], back[:, 1, 0], back[:, 1, 1], back[:, 2, 2] = cd, sd, -sd, cd, 1.0
        Jp = back.copy()
        Jp[:, :2, 2] = np.einsum("nij,nj->ni", back[:, :2, :2], np.column_stack([-d[:, 1], d[:, 0]]))
        return out, Jp

    def _sighting_errors(self, st: State, jacobians: bool, parameters: bool):
        """Raw (predicted - measured) reading and bearing errors, their pose Jacobians and parameter columns."""
        n_t = self.n_theta
        n_r, n_b = len(self.r_idx), len(self.b_idx)
        if not self.sensor_effects:
            pr, Jpr = self.sighting_poses(st, self.r_idx)
            pb, Jpb = self.sighting_poses(st, self.b_idx)
            er, Jr = factors.reading.error(pr, st.poly[None], self.r_lm, self.log.obs_reading[self.r_idx], self.basis)
            eb, Jb = factors.bearing.error(pb, self.b_lm, self.log.obs_bearing[self.b_idx])
            Hr, Hb = Jr[0][:, 0], Jb[0][:, 0]
            Tr = Tb = None
            if jacobians and parameters:
                Tr, Tb = np.zeros((n_r, n_t)), np.zeros((n_b, n_t))
                Tr[:, 3 * self.A:3 * self.A + self.D] = Jr[1][:, 0]
            if self.obs_shift is not None:
                Hr, Hb = np.einsum("ni,nij->nj", Hr, Jpr), np.einsum("ni,nij->nj", Hb, Jpb)
            return er[:, 0], eb[:, 0], Hr, Hb, Tr, Tb
        ctx = self.sensor_context(st)
        ls_eff = [s for e, s in self.sensor_effects if not e.noise_only]
        uses_velocity = any(getattr(e, "uses_velocity", False) for e, _ in self.sensor_effects)
        (er, Jr), (eb, Jb) = factors.effect_sighting.error(
            self._sensor_fn(ctx), st.poses, st.poly, st.theta, self.ls_index, ls_eff, self.obs_knot, self.r_idx,
            self.b_idx, self.log.obs_reading, self.log.obs_bearing, jacobians,
            ctx["velocity"] if uses_velocity else None)
        if not jacobians:
            return er, eb, None, None, None, None
        Tr = Tb = None
        if parameters:
            vel_row = self.lay.seg_action[np.clip(self.log.obs_step - 1, 0, self.lay.n_poses - 2)]

            def columns(J, idx):
                out = np.zeros((len(idx), n_t))
                rows_n = np.arange(len(idx))
                for c in range(3):          # the velocity the latency uses is the table's (effects aside)
                    out[rows_n, 3 * vel_row[idx] + c] += J["velocity"][:, c]
                out[:, 3 * self.A:3 * self.A + self.D] = J["poly"]
                if J["theta"] is not None:
                    out[:, 3 * self.A + self.D:] = J["theta"]
                return out

            Tr, Tb = columns(Jr, self.r_idx), columns(Jb, self.b_idx)
        return er, eb, Jr["pose"], Jb["pose"], Tr, Tb

    def rows(self, st: State, jacobians: bool = True, parameters: bool = True) -> Rows:
        """Every factor's whitened residual and (``jacobians``) Jacobians; ``parameters=False`` leaves out
        the parameter columns (a poses-only solve)."""
        ae, aJ = self._motion_rows(st, jacobians, parameters)
        er, eb, Jpr, Jpb, Tr, Tb = self._sighting_errors(st, jacobians, parameters)
        zr = er / (self.reading_sigma * self.r_scale[self.r_idx])
        zb = eb / self.bearing_sigma
        wr, wb = self.weight[self.r_idx], self.weight[self.b_idx]
        loss = float(np.sum(wr * robust.huber_loss(zr, self.k)) + np.sum(wb * robust.huber_loss(zb, self.k)))
        # a wild sighting pulls like one HUBER sigmas off, no more; an outlier by its inlier weight
        fr = robust.huber(zr, self.k) * np.sqrt(wr)
        fb = robust.huber(zb, self.k) * np.sqrt(wb)
        re, be = zr * fr, zb * fb
        rJ, bJ, bJt = [None, None], None, None
        if jacobians:
            gr = (fr / (self.reading_sigma * self.r_scale[self.r_idx]))[:, None]
            gb = (fb / self.bearing_sigma)[:, None]
            rJ = [Jpr * gr, None if Tr is None else Tr * gr]
            bJ, bJt = Jpb * gb, None if Tb is None else Tb * gb
        pj = np.concatenate([np.full(3 * self.A, 1 / G.VELOCITY_PRIOR_SIGMA), np.full(self.D, 1 / G.POLY_PRIOR_SIGMA),
                             1 / self.prior_sigma])
        pe = (self.pack(st) - np.concatenate([np.zeros(3 * self.A + self.D), self.prior_mean])) * pj
        P0 = st.poses[0, 2]
        he = np.zeros(0) if self.anchor is None else np.array([wrap(P0 - self.anchor) / G.ANCHOR_SIGMA])
        knot = self.obs_knot[self.s_idx]
        se, sJ = factors.standoff.error(st.poses[knot], self.obs_lmxy[self.s_idx])
        on = se > 0
        return Rows(ae, aJ, re, rJ, be, bJ, bJt, pe, pj, loss, he, (knot[on], se[on], sJ[on]))

    def sighting_rows(self, r: Rows, parameters: bool = True):
        """Knot, pose and parameter Jacobians and residuals of the sighting rows, then the pose-only rows (the
        heading anchor, the standoff)."""
        hk, hJ = G.anchor_rows(r.anchor_e)
        sk, se, sJ = r.standoff
        n_pose_only = len(hk) + len(sk)
        Jt = (np.concatenate([r.reading_J[1], r.bearing_Jt, np.zeros((n_pose_only, self.n_theta))]) if parameters
              else np.zeros((len(r.reading_e) + len(r.bearing_e) + n_pose_only, 0)))
        return (np.concatenate([self.r_knot, self.b_knot, hk, sk]),
                np.concatenate([r.reading_J[0], r.bearing_J, hJ, sJ]), Jt,
                np.concatenate([r.reading_e, r.bearing_e, r.anchor_e, se]))

    def cost(self, st: State) -> float:
        """GTSAM's error: half the sum of squared whitened residuals, sightings through Huber's loss."""
        r = self.rows(st, jacobians=False)
        return 0.5 * float(np.sum(r.action_e ** 2) + np.sum(r.prior_e ** 2) + np.sum(r.anchor_e ** 2)
                           + np.sum(r.standoff[1] ** 2)) + r.sighting_loss

    # ----------------------------------------------------------- linear algebra
    def linearize(self, st: State, poses_only: bool = False) -> gtsam.GaussianFactorGraph:
        """The Gauss-Newton system at ``st`` as a GTSAM graph: one factor per segment and per knot with
        sightings, on the poses and the parameter vector ``THETA`` (``poses_only``: parameters held)."""
        r = self.rows(st, parameters=not poses_only)
        K = self.lay.n_poses
        unit3 = gtsam.noiseModel.Unit.Create(3)
        g = gtsam.GaussianFactorGraph()
        Ha, Hb, Ht = r.action_J
        for i in range(K - 1):
            if poses_only:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], -r.action_e[i], unit3)
            else:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], THETA, Ht[i], -r.action_e[i], unit3)
        knot, Jp, Jt, e = self.sighting_rows(r, not poses_only)
        order = np.argsort(knot, kind="stable")
        knot, Jp, Jt, e = knot[order], Jp[order], Jt[order], e[order]
        cuts = np.flatnonzero(np.diff(knot)) + 1
        for s0, s1 in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(knot)]])):
            if s1 <= s0:
                continue
            nm = gtsam.noiseModel.Unit.Create(int(s1 - s0))
            if poses_only:
                g.add(X(int(knot[s0])), Jp[s0:s1], -e[s0:s1], nm)
            else:
                g.add(X(int(knot[s0])), Jp[s0:s1], THETA, Jt[s0:s1], -e[s0:s1], nm)
        if not poses_only:
            g.add(THETA, np.diag(r.prior_J), -r.prior_e, gtsam.noiseModel.Unit.Create(self.n_theta))
        return g

    def normal_equations(self, st: State, poses_only: bool = False) -> tuple:
        """Blocks of J^T J and J^T e: pose chain (D, B), coupling F, parameter block and gradients."""
        r = self.rows(st, parameters=not poses_only)
        Ha, Hb, Ht = r.action_J
        if poses_only:
            Ht, prior_J, prior_e = np.zeros((len(Ha), 3, 0)), np.zeros(0), np.zeros(0)
        else:
            prior_J, prior_e = r.prior_J, r.prior_e
        return chain.normal_equations(Ha, Hb, Ht, r.action_e, *self.sighting_rows(r, not poses_only), prior_J, prior_e,
                                      poses_only)

    def solve_damped(self, neq: tuple, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Damped Gauss-Newton step (dp, dtheta) from :meth:`normal_equations` (equals GTSAM's solve)."""
        return chain.solve_arrow(*neq, lam)

    def retract(self, st: State, delta) -> State:
        """Apply a step given as a ``gtsam.VectorValues`` or as arrays (dp (K, 3), dtheta or empty)."""
        K = self.lay.n_poses
        if isinstance(delta, gtsam.VectorValues):
            d = np.array([delta.at(X(i)) for i in range(K)])
            dth = np.asarray(delta.at(THETA)) if delta.exists(THETA) else None
        else:
            d, dth = delta
            dth = dth if len(dth) else None
        poses = G.retract_poses(st.poses, d)
        if dth is None:
            return State(poses, st.velocities, st.poly, st.theta)
        x = self.pack(st) + dth
        theta = st.theta.copy()
        theta[self.ls_index] = x[3 * self.A + self.D:]
        return State(poses, x[:3 * self.A].reshape(-1, 3), x[3 * self.A:3 * self.A + self.D], theta)

    def keys_dims(self) -> list[tuple[int, int]]:
        return [(X(i), 3) for i in range(self.lay.n_poses)] + [(THETA, self.n_theta)]

    def jacobian(self, st: State):
        """Whitened sparse Jacobian (rows: action x/y/theta interleaved, reading, bearing, priors, anchor), the
        residual, and the row groups of each channel (for the noise step's hat traces)."""
        r = self.rows(st)
        K, n_t = self.lay.n_poses, self.n_theta
        S = K - 1
        n_r, n_b = len(r.reading_e), len(r.bearing_e)
        Ha, Hb, Ht = r.action_J
        seg = np.arange(S)
        blocks = []

        def block(row0, J, col0):
            n, m, dd = J.shape
            rr = np.broadcast_to(row0[:, None, None] + np.arange(m)[None, :, None], J.shape)
            cc = np.broadcast_to(col0[:, None, None] + np.arange(dd)[None, None, :], J.shape)
            nz = J != 0
            blocks.append((rr[nz], cc[nz], J[nz]))

        block(3 * seg, Ha, 3 * seg)
        block(3 * seg, Hb, 3 * (seg + 1))
        block(3 * seg, Ht, np.full(S, 3 * K))
        ro = 3 * S
        block(ro + np.arange(n_r), r.reading_J[0][:, None, :], 3 * self.r_knot)
        block(ro + np.arange(n_r), r.reading_J[1][:, None, :], np.full(n_r, 3 * K))
        block(ro + n_r + np.arange(n_b), r.bearing_J[:, None, :], 3 * self.b_knot)
        block(ro + n_r + np.arange(n_b), r.bearing_Jt[:, None, :], np.full(n_b, 3 * K))
        po, n_h = ro + n_r + n_b, len(r.anchor_e)
        blocks.append((po + np.arange(n_t), 3 * K + np.arange(n_t), r.prior_J))
        hk, hJ = G.anchor_rows(r.anchor_e)
        block(po + n_t + np.arange(n_h), hJ[:, None, :], 3 * hk)
        sk, se, sJ = r.standoff
        block(po + n_t + n_h + np.arange(len(sk)), sJ[:, None, :], 3 * sk)
        rows, cols, vals = (np.concatenate(x) for x in zip(*blocks))
        A = sp.csr_matrix((vals, (rows, cols)), shape=(po + n_t + n_h + len(sk), 3 * K + n_t))
        e = np.concatenate([r.action_e.ravel(), r.reading_e, r.bearing_e, r.prior_e, r.anchor_e, se])
        groups = {"forward": np.arange(0, ro, 3), "lateral": np.arange(1, ro, 3),
                  "turn": np.arange(2, ro, 3), "reading": ro + np.arange(n_r),
                  "bearing": ro + n_r + np.arange(n_b)}
        return A, e, groups

    # ------------------------------------------------------------------ noise
    def outlier_fraction(self, theta: np.ndarray) -> float:
        return float(sum(e.outlier_fraction(theta[s]) for e, s in self.sensor_effects))

    def observation_terms(self, st: State) -> dict:
        """Raw residuals (measured - predicted), distances and per-observation log densities."""
        pr = self.predictions(st)
        rr = self.log.obs_reading - pr["reading"]
        rb = wrap(self.log.obs_bearing - pr["bearing"])
        d = pr["distance"]
        scale = reading_scale(self.sensor_effects, st.theta, d)
        m = mixture_terms(rr, rb, self.reading_sigma * scale, self.bearing_sigma, self.outlier_fraction(st.theta),
                          self.reading_span)
        return {"reading": rr, "bearing": rb, "distance": d, "scale": scale, "log_density": m["log_density"],
                "weight": m["weight"]}

    def refresh_noise_state(self, st: State) -> None:
        """Per-observation reading scales and inlier weights at ``st`` (held fixed while least squares runs)."""
        t = self.observation_terms(st)
        self.r_scale = t["scale"]
        self.weight = t["weight"]

    def log_likelihood_terms(self, st: State) -> dict:
        """The Laplace log-likelihood's parts: motion and observation log densities at ``st``, the
        Gaussian constant of the integrated poses and half the log det of their information."""
        r = self.rows(st, parameters=False)
        lm = -0.5 * np.sum(r.action_e ** 2) - np.sum(np.log(self.motion_sigma)) \
            - 0.5 * r.action_e.size * np.log(2 * np.pi)
        t = self.observation_terms(st)
        D, B = chain.information_blocks(self, st, rows=r)
        try:
            _, _, logdet = chain.select_inverse(D, B)
        except np.linalg.LinAlgError:     # singular to machine precision: no Laplace value (NaN, as a negative
            logdet = np.nan               # determinant gives), so no candidate is supported on its strength
        return {"motion": float(lm), "observation": float(np.sum(t["log_density"][self.obs_mask])),
                "pose_constant": 1.5 * self.lay.n_poses * np.log(2 * np.pi), "half_log_det": 0.5 * float(logdet)}

    def log_likelihood(self, st: State) -> float:
        """Laplace log p(O | model): data densities at the pose mode minus half log det of the pose information."""
        t = self.log_likelihood_terms(st)
        return float(t["motion"] + t["observation"] + t["pose_constant"] - t["half_log_det"])
