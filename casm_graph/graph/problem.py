"""The factor graph of one log: poses, the action model's parameters, sensor curve and any effects' parameters.

One class serves every graph of every log: the action model is a part (:mod:`casm_graph.graph.actions`: a
velocity table, or a command map), the sensor two optional channels (reading through the curve of distance;
bearing). Calibration's coarse and full graphs, graph-em's E-step, the effect fits, the diagnosis and the
uncertainty step all build it. The parameters (the action part's, the curve's coefficients, the least-squares
parameters of the effects) travel as one vector, the dense arm of an arrow whose shaft is the pose chain.
Without effects the factors are the analytic ones of :mod:`factors`; an effect's hooks add the chained
derivatives of :mod:`factors.effect_motion` and :mod:`factors.effect_sighting`. Noise-only effects
(range-dependent noise, false detections) set per-observation scales and inlier weights that the noise step
re-estimates, as for the sigmas. Sightings count through Huber's loss unless ``huber=False``.
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
from casm_graph.graph.actions import default_layout, part_for
from casm_graph.graph.augmented import (parameter_prior, parameter_slices, reading_scale,
                                        sensor_function, theta_from_model)
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects import Effect
from casm_graph.models.effects.false_detections import mixture_terms, reading_span
from casm_graph.models.model import Model

THETA = T(0)                      # the parameter vector's key in GTSAM graphs: table rows, curve, effects


@dataclass
class State:
    """Variables: the poses of the layout's knots, the action model's parameters, the polynomial, and the effects'
    parameters."""

    poses: np.ndarray                # (K, 3)
    action: np.ndarray               # a table's (A, 3) velocities, or a command map's coefficients (P,)
    poly: np.ndarray                 # (D,)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))   # every effect parameter, noise-only ones too

    @property
    def velocities(self) -> np.ndarray:
        """An action table's (A, 3) rows."""
        return self.action

    @property
    def params(self) -> np.ndarray:
        """A command map's coefficients."""
        return self.action


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

    ``lay`` is the pose layout (the action part's default when omitted: a pose every step of an action
    table, knots every 0.25 s of a command log). ``weight`` gives each sighting's inlier weight (a
    false-detection mixture's), ``obs_mask`` hides sightings (held-out folds, pruned outliers); ``gate``, a
    pair of (reading, bearing) masks, sets channels of sightings aside from least squares as gross outliers
    (a false-detection mixture still counts them). ``poses`` (the knots) sets the per-observation
    noise state (scales, inlier weights) and place-dependent motion noise there, fixed for the problem's
    life. ``anchor`` holds the first pose's heading there (``graph.table.ANCHOR_SIGMA``): without bearings
    every heading and body velocity may turn together, ranges and motion unchanged.
    """

    def __init__(self, log: Log, model: Model, effects: list[Effect] = (), *, lay=None,
                 theta: np.ndarray | None = None, obs_mask: np.ndarray | None = None, gate=None,
                 weight: np.ndarray | None = None,
                 huber: bool = True, anchor: float | None = None, poses: np.ndarray | None = None):
        self.log, self.model, self.effects = log, model, list(effects)
        self.anchor = anchor
        self.lay = lay = default_layout(log, model) if lay is None else lay
        self.k = robust.HUBER if huber else np.inf
        self.slices = parameter_slices(self.effects)
        ls = np.concatenate([np.arange(s.start, s.stop) for e, s in zip(self.effects, self.slices)
                             if not e.noise_only] + [np.zeros(0, int)]).astype(int)
        self.ls_index = ls                                   # effect parameters that least squares moves
        self.motion_effects = [(e, s) for e, s in zip(self.effects, self.slices) if e.channel == "motion"]
        self.sensor_effects = [(e, s) for e, s in zip(self.effects, self.slices) if e.channel == "sensor"]
        self.noise_effects = [(e, s) for e, s in self.sensor_effects if e.noise_only]
        self.action = part_for(lay)(log, model, lay, self.motion_effects, ls, self.effects)
        self.n_action, self.D = self.action.n, len(model.reading_poly)
        self.n_theta = self.n_action + self.D + len(ls)
        self.basis = model.reading_basis
        self.motion_sigma = self.action.motion_sigma(model, poses)
        # observations
        n_obs = len(log.obs_t)
        self.obs_mask = np.ones(n_obs, bool) if obs_mask is None else np.asarray(obs_mask, bool)
        gate_r, gate_b = (np.ones(n_obs, bool),) * 2 if gate is None else gate
        self.obs_knot = lay.obs_knot
        self.obs_lm = log.landmark_index
        self.obs_lmxy = log.landmark_xy[self.obs_lm]
        self.pan = log.camera_pan
        self.r_sel = np.isfinite(log.obs_reading) & self.obs_mask & np.asarray(gate_r, bool)
        self.b_sel = np.isfinite(log.obs_bearing) & self.obs_mask & np.asarray(gate_b, bool)
        self.r_idx, self.b_idx = np.flatnonzero(self.r_sel), np.flatnonzero(self.b_sel)
        self.r_knot, self.b_knot = self.obs_knot[self.r_idx], self.obs_knot[self.b_idx]
        self.r_lm, self.b_lm = self.obs_lmxy[self.r_idx], self.obs_lmxy[self.b_idx]
        self.s_idx = np.union1d(self.r_idx, self.b_idx)      # every sighting in the graph: its pose keeps off the landmark
        self.measured = np.isfinite(log.obs_reading) | np.isfinite(log.obs_bearing)   # sightings with any channel
        # a coarse layout's sighting lies some steps from its knot: the knot's pose is carried there by the
        # model's velocity of the action between, held for the problem's life like the noise levels
        self.obs_carry = self.action.carry(model)
        self.reading_sigma, self.bearing_sigma = float(model.reading_sigma), float(model.bearing_sigma)
        self.reading_span = reading_span(log.obs_reading)
        self.r_scale = np.ones(n_obs)
        self.weight = np.ones(n_obs) if weight is None else np.asarray(weight, float).copy()
        th0 = theta if theta is not None else theta_from_model(self.effects, model)
        self.theta_noise = np.asarray(th0, float).copy()
        a_mean, a_sigma = self.action.prior(model)
        e_mean, e_sigma = parameter_prior(self.effects, self.slices)
        self.prior_mean = np.concatenate([a_mean, np.zeros(self.D), e_mean])
        self.prior_sigma = np.concatenate([a_sigma, np.full(self.D, G.POLY_PRIOR_SIGMA), e_sigma])
        self.mixed = any(e.mixture for e, _ in self.noise_effects)
        if poses is not None and self.noise_effects:
            self.refresh_noise_state(self.state(poses, model))

    @property
    def counts(self) -> dict[str, float]:
        """Each sighting channel's row count, its sightings' inlier weights summed."""
        return {"reading": float(np.sum(self.weight[self.r_idx])), "bearing": float(np.sum(self.weight[self.b_idx]))}

    # ------------------------------------------------------------------ state
    def state(self, poses: np.ndarray, model: Model, theta: np.ndarray | None = None) -> State:
        """The variables at ``poses`` and ``model``'s action parameters and curve; the effects' at ``theta`` (the
        problem's own when None)."""
        th = self.theta_noise.copy() if theta is None else np.asarray(theta, float).copy()
        return State(np.asarray(poses, float).copy(), self.action.params(model),
                     np.asarray(model.reading_poly, float).copy(), th)

    def with_state(self, model: Model, st: State) -> Model:
        """``model`` with the action parameters, curve and least-squares effect parameters of ``st``."""
        model = self.action.with_params(model, st.action).with_(reading_poly=st.poly.copy())
        described = {e.name: e.describe(st.theta[s]) for e, s in zip(self.effects, self.slices) if not e.noise_only}
        return model.with_(effects={**model.effects, **described}) if described else model

    def pack(self, st: State) -> np.ndarray:
        return np.concatenate([np.ravel(st.action), st.poly, st.theta[self.ls_index]])

    def effects_std(self, x_std: np.ndarray) -> dict:
        """Each least-squares effect parameter's std, by name, from the std of the parameter vector's entries."""
        col = {int(c): self.n_action + self.D + j for j, c in enumerate(self.ls_index)}
        return {e.name: {p: float(x_std[col[i]]) for p, i in zip(e.params, range(s.start, s.stop))}
                for e, s in zip(self.effects, self.slices) if not e.noise_only}

    # ------------------------------------------------------------- evaluation
    def sensor_context(self, st: State) -> dict:
        """Context of every observation under ``st`` (the velocity the action part gives a sighting)."""
        v, _ = self.action.sighting_velocity(st.poses, st.action, st.theta, jacobian=False)
        return {"t": self.log.obs_t - self.log.t[0], "landmark": self.obs_lm, "pan": self.pan, "velocity": v}

    def _sensor_fn(self, ctx):
        return sensor_function(self.sensor_effects, ctx, self.obs_lmxy, self.basis)

    def predictions(self, st: State) -> dict:
        """Predicted reading, bearing and distance of every observation (masked or not)."""
        fn = self._sensor_fn(self.sensor_context(st))
        idx = np.arange(len(self.log.obs_t))
        pred, bearing, d = fn(st.theta, st.poses[self.obs_knot], st.poly, idx)
        return {"reading": pred, "bearing": wrap(bearing), "distance": d}

    def _motion_rows(self, st: State, jacobians: bool, parameters: bool):
        e, (Ha, Hb), Hx, Hls = self.action.motion(st.poses, st.action, st.theta, jacobians, parameters)
        w = 1.0 / self.motion_sigma
        ae = e * w
        if not jacobians:
            return ae, [None, None, None]
        Ht = None
        if parameters:
            Ht = np.zeros((len(e), 3, self.n_theta))
            Ht[:, :, :self.n_action] = Hx * w[:, :, None]
            if Hls is not None:
                Ht[:, :, self.n_action + self.D:] = Hls * w[:, :, None]
        return ae, [Ha * w[:, :, None], Hb * w[:, :, None], Ht]

    def motion_residual(self, st: State) -> np.ndarray:
        """(S, 3) motion residual of every segment (body-frame pose difference minus the model's), unwhitened."""
        return self.action.motion(st.poses, st.action, st.theta, jacobians=False)[0]

    def sighting_poses(self, st: State, idx: np.ndarray):
        """Poses of sightings ``idx``: their knots' (a pose every step), or on a coarse layout each knot's pose
        carried over the steps to the sighting (``obs_carry``); with the tangent derivative (n, 3, 3) of each
        with respect to the knot's pose (None at a pose every step)."""
        p = st.poses[self.obs_knot[idx]]
        if self.obs_carry is None:
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
                Tr[:, self.n_action:self.n_action + self.D] = Jr[1][:, 0]
            if self.obs_carry is not None:
                Hr, Hb = np.einsum("ni,nij->nj", Hr, Jpr), np.einsum("ni,nij->nj", Hb, Jpb)
            return er[:, 0], eb[:, 0], Hr, Hb, Tr, Tb
        v, dv = self.action.sighting_velocity(st.poses, st.action, st.theta, jacobian=jacobians and parameters)
        ctx = {"t": self.log.obs_t - self.log.t[0], "landmark": self.obs_lm, "pan": self.pan, "velocity": v}
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
            na, D = self.n_action, self.D

            def columns(J, idx):
                out = np.zeros((len(idx), n_t))
                # the velocity a latency uses is the action model's (effects aside)
                out[:, :na] = np.einsum("nc,nck->nk", J["velocity"], dv[idx])
                out[:, na:na + D] = J["poly"]
                if J["theta"] is not None:
                    out[:, na + D:] = J["theta"]
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
        pj = 1 / self.prior_sigma
        pe = (self.pack(st) - self.prior_mean) * pj
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
            return State(poses, st.action, st.poly, st.theta)
        x = self.pack(st) + dth
        na, D = self.n_action, self.D
        theta = st.theta.copy()
        theta[self.ls_index] = x[na + D:]
        return State(poses, x[:na].reshape(self.action.shape), x[na:na + D], theta)

    def keys_dims(self) -> list[tuple[int, int]]:
        return [(X(i), 3) for i in range(self.lay.n_poses)] + [(THETA, self.n_theta)]

    def jacobian(self, st: State, poses_only: bool = False):
        """Whitened sparse Jacobian (rows: action x/y/theta interleaved, reading, bearing, priors, anchor,
        standoff), the residual, and the row groups of each channel (for the noise step's hat traces);
        ``poses_only``: the parameters' columns and prior rows left out (parameters held)."""
        r = self.rows(st, parameters=not poses_only)
        K, n_t = self.lay.n_poses, (0 if poses_only else self.n_theta)
        S = K - 1
        if poses_only:
            r.action_J[2] = np.zeros((S, 3, 0))
            r.reading_J[1], r.bearing_Jt = np.zeros((len(r.reading_e), 0)), np.zeros((len(r.bearing_e), 0))
            r.prior_e, r.prior_J = np.zeros(0), np.zeros(0)
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

    def set_aside(self, model: Model) -> int:
        """Sightings of a channel ``model`` measures that the gate set aside (gross outliers)."""
        log = self.log
        return int(np.sum(self.obs_mask & ((np.isfinite(log.obs_reading) & ~self.r_sel & model.has("reading"))
                                           | (np.isfinite(log.obs_bearing) & ~self.b_sel & model.has("bearing")))))

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
