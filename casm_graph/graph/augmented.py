"""The factor graph of one log with effects added: their parameters become graph variables.

Poses stay one ``Pose2`` variable per step; the velocity table, the sensor polynomial and the
least-squares parameters of every effect travel together as one vector variable ``T(0)`` (an
action step may touch two table rows and an effect, more keys than GTSAM's Python Jacobian
factors take). The effect factors of :mod:`factors.effect_motion` and :mod:`factors.effect_sighting`
give residuals and Jacobians; noise-only effects (range-dependent noise, false detections) set
per-observation scales and inlier weights that the noise step re-estimates, as for the sigmas.
The Jacobians are exact (tests/test_effects.py) except that the velocity a latency shift uses is
differentiated through the table row alone, not through other motion effects.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
from gtsam.symbol_shorthand import T, X

import factors
from casm_graph.graph import chain
from casm_graph.graph import noise as noisemod
from casm_graph.graph import table as G
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects import Effect
from casm_graph.models.effects import get as get_effect
from casm_graph.models.effects.false_detections import mixture_terms, reading_span
from casm_graph.models.model import Model

THETA = T(0)
EFFECT_PRIOR_SCALE = 1e4          # weak prior (in units of each parameter's scale) where an effect has none


@dataclass
class AState:
    """Variables: poses at every step, the table, the polynomial, and the effects' parameters."""

    poses: np.ndarray
    velocities: np.ndarray
    poly: np.ndarray
    theta: np.ndarray                # all effect parameters, least-squares and noise-only alike


@dataclass
class ARows:
    """Whitened residuals and Jacobians; the names the chain marginals read match :class:`graph.Rows`."""

    action_e: np.ndarray
    action_J: list                   # [Ha (S,3,3), Hb (S,3,3), Htheta (S,3,n)]
    reading_e: np.ndarray
    reading_J: list                  # [Hp (n,3), Htheta (n, n_theta)]
    bearing_e: np.ndarray
    bearing_J: np.ndarray            # (n, 3)
    bearing_Jt: np.ndarray           # (n, n_theta)
    prior_e: np.ndarray
    prior_J: np.ndarray              # (n_theta,) diagonal
    anchor_e: np.ndarray = field(default_factory=lambda: np.zeros(0))   # the first heading's hold (graph.Problem's)


def instantiate(names_or_effects, log: Log) -> list[Effect]:
    """Effect instances for ``log`` from names, classes or instances."""
    out = []
    for e in names_or_effects:
        if isinstance(e, str):
            e = get_effect(e)
        out.append(e(log) if isinstance(e, type) else e)
    return out


def theta_from_model(effects: list[Effect], model: Model) -> np.ndarray:
    """Effect parameters stored in ``model.effects``, or each effect's start where absent (what else an entry
    records, each effect takes back through ``restore``)."""
    vals = []
    for e in effects:
        stored = model.effects.get(e.name, {})
        e.restore(stored)
        vals.extend(float(stored.get(p, s)) for p, s in zip(e.params, e.start))
    return np.array(vals, float)


def reading_scale(effect_slices, theta: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Each reading's sigma factor: the product of the effects' ``reading_scale`` at ``distance`` (``effect_slices``:
    (effect, its slice of ``theta``) pairs; 1 everywhere without a noise effect)."""
    scale = np.ones(len(distance))
    for e, s in effect_slices:
        scale = scale * e.reading_scale(theta[s], distance, {})
    return scale


def parameter_slices(effects: list[Effect]) -> list[slice]:
    """Each effect's slice of the stacked parameter vector theta, in the effects' order."""
    cuts = np.concatenate([[0], np.cumsum([len(e.params) for e in effects])]).astype(int)
    return [slice(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:])]


def parameter_prior(effects: list[Effect], slices: list[slice]) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sigma) of the prior on the least-squares effect parameters: each effect's own, else weak around 0."""
    pm, ps = [np.zeros(0)], [np.zeros(0)]
    for e, s in zip(effects, slices):
        if e.noise_only:
            continue
        pr = e.prior()
        if pr is None:
            pm.append(np.zeros(s.stop - s.start))
            ps.append(EFFECT_PRIOR_SCALE * np.maximum(np.asarray(e.scale, float), 1e-6))
        else:
            pm.append(np.asarray(pr[0], float))
            ps.append(np.asarray(pr[1], float))
    return np.concatenate(pm), np.concatenate(ps)


def motion_function(motion_effects, ctx: dict, theta: np.ndarray):
    """The velocity a step runs under ``motion_effects`` ((effect, slice) pairs) as a function of the
    action model's velocity ``v``, the previous one, the pose and (optionally) the parameters."""

    def bound(v, v_prev, pose, th=None):
        c = {**ctx, "v_prev": v_prev, "pose": pose}
        th = theta if th is None else th
        for e, s in motion_effects:
            v = e.velocity(th[s], v, c)
        return v

    return bound


def sensor_function(sensor_effects, ctx: dict, landmark_xy: np.ndarray, basis: str = "distance"):
    """Predicted reading, bearing and distance of observations ``idx`` under ``sensor_effects`` ((effect,
    slice) pairs), as a function of the parameters, the poses and the sensor curve's coefficients (in
    ``basis``, :mod:`factors.reading`); ``landmark_xy`` per observation."""

    def fn(theta, pose, poly, idx, velocity=None):
        c = {k: (v[idx] if isinstance(v, np.ndarray) else v) for k, v in ctx.items()}
        c["pose"] = pose
        if velocity is not None:
            c["velocity"] = velocity[idx]
        p, lm = pose, landmark_xy[idx]
        for e, s in sensor_effects:
            p, lm = e.geometry(theta[s], p, lm, c)
        rel = lm - p[:, :2]
        d = np.hypot(rel[:, 0], rel[:, 1])
        bearing = np.arctan2(rel[:, 1], rel[:, 0]) - p[:, 2]
        c.update(distance=d, bearing=wrap(bearing), image_angle=wrap(bearing - c["pan"]))
        pred = factors.reading.curve(d, poly, basis)
        for e, s in sensor_effects:
            pred = e.reading(theta[s], pred, c)
        return pred, bearing, d

    return fn


class EffectProblem:
    """One log, a model with noise levels held fixed, and effects; evaluated and linearised in numpy."""

    def __init__(self, log: Log, model: Model, effects: list[Effect], theta: np.ndarray | None = None,
                 obs_mask: np.ndarray | None = None, anchor: float | None = None):
        self.log, self.model, self.effects = log, model, effects
        self.anchor = anchor                     # the first heading held (ranges only: graph.heading_anchor)
        self.lay = G.layout(log, model, stride=1)
        lay = self.lay
        self.slices = parameter_slices(effects)
        self.n_eff = self.slices[-1].stop if self.slices else 0
        ls = np.concatenate([np.arange(s.start, s.stop) for e, s in zip(effects, self.slices)
                             if not e.noise_only] + [np.zeros(0, int)]).astype(int)
        self.ls_index = ls                                   # effect parameters that least squares moves
        self.A, self.D = lay.n_actions, len(model.reading_poly)
        self.n_theta = 3 * self.A + self.D + len(ls)
        self.motion_effects = [(e, s) for e, s in zip(effects, self.slices) if e.channel == "motion"]
        self.sensor_effects = [(e, s) for e, s in zip(effects, self.slices) if e.channel == "sensor"]
        # motion context (one row per step)
        act = lay.seg_action
        change = np.concatenate([[True], act[1:] != act[:-1]])
        start_idx = np.maximum.accumulate(np.where(change, np.arange(len(act)), 0))
        prev = np.where(start_idx > 0, act[np.maximum(start_idx - 1, 0)], act)
        t_rel = log.t - log.t[0]
        self.m_ctx = {"t": t_rel, "since": t_rel - t_rel[start_idx], "dt": log.dt.copy()}
        self.prev_row = prev
        self.motion_sigma = np.asarray(model.motion_noise, float)[None, :] * np.ones((lay.n_poses - 1, 1))
        # observations
        n_obs = len(log.obs_t)
        self.obs_mask = np.ones(n_obs, bool) if obs_mask is None else np.asarray(obs_mask, bool)
        self.obs_knot = lay.obs_knot
        self.obs_lm = log.landmark_index
        self.obs_lmxy = log.landmark_xy[self.obs_lm]
        self.pan = log.camera_pan
        self.r_ok = np.isfinite(log.obs_reading) & self.obs_mask
        self.b_ok = np.isfinite(log.obs_bearing) & self.obs_mask
        self.r_idx, self.b_idx = np.flatnonzero(self.r_ok), np.flatnonzero(self.b_ok)
        self.r_knot, self.b_knot = self.obs_knot[self.r_idx], self.obs_knot[self.b_idx]
        self.reading_sigma, self.bearing_sigma = float(model.reading_sigma), float(model.bearing_sigma)
        self.reading_span = reading_span(log.obs_reading)
        self.r_scale = np.ones(n_obs)
        self.weight = np.ones(n_obs)
        th0 = theta if theta is not None else theta_from_model(effects, model)
        self.theta_noise = np.asarray(th0, float).copy()
        self.prior_mean, self.prior_sigma = parameter_prior(effects, self.slices)

    # ------------------------------------------------------------------ state
    def state(self, poses: np.ndarray, model: Model, theta: np.ndarray | None = None) -> AState:
        th = self.theta_noise.copy() if theta is None else np.asarray(theta, float).copy()
        return AState(np.asarray(poses, float).copy(), np.asarray(model.velocities, float).copy(),
                      np.asarray(model.reading_poly, float).copy(), th)

    def pack(self, st: AState) -> np.ndarray:
        return np.concatenate([st.velocities.ravel(), st.poly, st.theta[self.ls_index]])

    # ------------------------------------------------------------- evaluation
    def step_velocity(self, st: AState) -> np.ndarray:
        """(S, 3) velocity each step runs under the table and the motion effects."""
        return factors.effect_motion.velocity(self._motion_fn(st), st.velocities[self.lay.seg_action],
                                              st.velocities[self.prev_row], st.poses[:-1])

    def _motion_fn(self, st: AState):
        return motion_function(self.motion_effects, self.m_ctx, st.theta)

    def sensor_context(self, st: AState) -> dict:
        """Context of every observation under ``st`` (velocity from the previous step)."""
        v = self.step_velocity(st)
        step = np.clip(self.log.obs_step - 1, 0, len(v) - 1)
        return {"t": self.log.obs_t - self.log.t[0], "landmark": self.obs_lm, "pan": self.pan,
                "velocity": v[step]}

    def _sensor_fn(self, ctx):
        return sensor_function(self.sensor_effects, ctx, self.obs_lmxy, self.model.reading_basis)

    def predictions(self, st: AState) -> dict:
        """Predicted reading, bearing and distance of every observation (masked or not)."""
        fn = self._sensor_fn(self.sensor_context(st))
        idx = np.arange(len(self.log.obs_t))
        pred, bearing, d = fn(st.theta, st.poses[self.obs_knot], st.poly, idx)
        return {"reading": pred, "bearing": wrap(bearing), "distance": d}

    def rows(self, st: AState, jacobians: bool = True) -> ARows:
        lay, n_t = self.lay, self.n_theta
        P = st.poses
        S = lay.n_poses - 1
        # motion
        e, (Ha, Hb, Hv), dv = factors.effect_motion.error(
            self._motion_fn(st), P, st.velocities, lay.seg_action, self.prev_row, self.log.dt,
            st.theta, self.ls_index, [s for _, s in self.motion_effects])
        w = 1.0 / self.motion_sigma
        ae = e * w
        Ht = np.zeros((S, 3, n_t))
        if jacobians:
            rows3 = np.arange(S)
            own, prev = dv["own"] * w[:, :, None], dv["prev"] * w[:, :, None]
            for c in range(3):             # one row per step in each statement: no repeated index, no add.at
                Ht[rows3, :, 3 * lay.seg_action + c] += own[:, :, c]
                Ht[rows3, :, 3 * self.prev_row + c] += prev[:, :, c]
            if dv["theta"] is not None:
                Ht[:, :, 3 * self.A + self.D:] = dv["theta"] * w[:, :, None]
            Ha = (Ha + dv["pose"]) * w[:, :, None]
            Hb = Hb * w[:, :, None]
        # sightings
        ctx = self.sensor_context(st)
        fn = self._sensor_fn(ctx)
        ls_eff = [s for e, s in self.sensor_effects if not e.noise_only]
        uses_velocity = any(getattr(e, "uses_velocity", False) for e, _ in self.sensor_effects)
        (er, Jr), (eb, Jb) = factors.effect_sighting.error(
            fn, P, st.poly, st.theta, self.ls_index, ls_eff, self.obs_knot, self.r_idx, self.b_idx,
            self.log.obs_reading, self.log.obs_bearing, jacobians,
            ctx["velocity"] if uses_velocity else None)
        wr = np.sqrt(self.weight[self.r_idx]) / (self.reading_sigma * self.r_scale[self.r_idx])
        wb = np.sqrt(self.weight[self.b_idx]) / self.bearing_sigma
        re, be = er * wr, eb * wb

        vel_row = lay.seg_action[np.clip(self.log.obs_step - 1, 0, S - 1)]

        def theta_cols(J, n, idx):
            out = np.zeros((n, n_t))
            if J is not None:
                rows_n = np.arange(n)
                for c in range(3):          # the velocity the latency uses is the table's (effects aside)
                    out[rows_n, 3 * vel_row[idx] + c] += J["velocity"][:, c]
                out[:, 3 * self.A:3 * self.A + self.D] = J["poly"]
                if J["theta"] is not None:
                    out[:, 3 * self.A + self.D:] = J["theta"]
            return out

        if jacobians:
            rJ = [Jr["pose"] * wr[:, None], theta_cols(Jr, len(er), self.r_idx) * wr[:, None]]
            bJ, bJt = Jb["pose"] * wb[:, None], theta_cols(Jb, len(eb), self.b_idx) * wb[:, None]
        else:
            rJ, bJ, bJt = [None, None], None, None
        pj = np.concatenate([np.full(3 * self.A, 1 / G.VELOCITY_PRIOR_SIGMA),
                             np.full(self.D, 1 / G.POLY_PRIOR_SIGMA), 1 / self.prior_sigma])
        pe = (self.pack(st) - np.concatenate([np.zeros(3 * self.A + self.D), self.prior_mean])) * pj
        he = np.zeros(0) if self.anchor is None else np.array([wrap(P[0, 2] - self.anchor) / G.ANCHOR_SIGMA])
        return ARows(ae, [Ha, Hb, Ht], re, rJ, be, bJ, bJt, pe, pj, he)

    def _sightings(self, r: ARows):
        """Knot, pose and parameter Jacobians and residuals of the sighting rows, the heading anchor last."""
        hk, hJ = G.anchor_rows(r.anchor_e)
        return (np.concatenate([self.r_knot, self.b_knot, hk]),
                np.concatenate([r.reading_J[0], r.bearing_J, hJ]),
                np.concatenate([r.reading_J[1], r.bearing_Jt, np.zeros((len(hk), self.n_theta))]),
                np.concatenate([r.reading_e, r.bearing_e, r.anchor_e]))

    def cost(self, st: AState) -> float:
        r = self.rows(st, jacobians=False)
        return 0.5 * float(np.sum(r.action_e ** 2) + np.sum(r.reading_e ** 2) + np.sum(r.bearing_e ** 2)
                           + np.sum(r.prior_e ** 2) + np.sum(r.anchor_e ** 2))

    # ----------------------------------------------------------- linear algebra
    def linearize(self, st: AState, poses_only: bool = False) -> gtsam.GaussianFactorGraph:
        r = self.rows(st)
        K = self.lay.n_poses
        unit3 = gtsam.noiseModel.Unit.Create(3)
        g = gtsam.GaussianFactorGraph()
        Ha, Hb, Ht = r.action_J
        for i in range(K - 1):
            if poses_only:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], -r.action_e[i], unit3)
            else:
                g.add(X(i), Ha[i], X(i + 1), Hb[i], THETA, Ht[i], -r.action_e[i], unit3)
        knot, Jp, Jt, e = self._sightings(r)
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

    def normal_equations(self, st: AState, poses_only: bool = False) -> tuple:
        """Blocks of J^T J and J^T e: pose chain (D, B), coupling F, parameter block and gradients."""
        r = self.rows(st)
        Ha, Hb, Ht = r.action_J
        return chain.normal_equations(Ha, Hb, Ht, r.action_e, *self._sightings(r), r.prior_J, r.prior_e, poses_only)

    def solve_damped(self, neq: tuple, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Damped Gauss-Newton step (dp, dtheta) from :meth:`normal_equations` (equals GTSAM's solve)."""
        return chain.solve_arrow(*neq, lam)

    def retract(self, st: AState, delta) -> AState:
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
            return AState(poses, st.velocities, st.poly, st.theta)
        x = self.pack(st) + dth
        theta = st.theta.copy()
        theta[self.ls_index] = x[3 * self.A + self.D:]
        return AState(poses, x[:3 * self.A].reshape(-1, 3), x[3 * self.A:3 * self.A + self.D], theta)

    def keys_dims(self) -> list[tuple[int, int]]:
        return [(X(i), 3) for i in range(self.lay.n_poses)] + [(THETA, self.n_theta)]

    def jacobian(self, st: AState):
        """Whitened sparse Jacobian with row groups per channel (for the noise step's hat traces)."""
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
        rows, cols, vals = (np.concatenate(x) for x in zip(*blocks))
        A = sp.csr_matrix((vals, (rows, cols)), shape=(po + n_t + n_h, 3 * K + n_t))
        e = np.concatenate([r.action_e.ravel(), r.reading_e, r.bearing_e, r.prior_e, r.anchor_e])
        groups = {"forward": np.arange(0, ro, 3), "lateral": np.arange(1, ro, 3),
                  "turn": np.arange(2, ro, 3), "reading": ro + np.arange(n_r),
                  "bearing": ro + n_r + np.arange(n_b)}
        return A, e, groups

    # ------------------------------------------------------------------ noise
    def outlier_fraction(self, theta: np.ndarray) -> float:
        return float(sum(e.outlier_fraction(theta[s]) for e, s in self.sensor_effects))

    def observation_terms(self, st: AState) -> dict:
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

    def refresh_noise_state(self, st: AState) -> None:
        """Per-observation reading scales and inlier weights at ``st`` (held fixed while least squares runs)."""
        t = self.observation_terms(st)
        self.r_scale = t["scale"]
        self.weight = t["weight"]

    def log_likelihood_terms(self, st: AState) -> dict:
        """The Laplace log-likelihood's parts: motion and observation log densities at ``st``, the
        Gaussian constant of the integrated poses and half the log det of their information."""
        r = self.rows(st)
        lm = -0.5 * np.sum(r.action_e ** 2) - np.sum(np.log(self.motion_sigma)) \
            - 0.5 * r.action_e.size * np.log(2 * np.pi)
        t = self.observation_terms(st)
        D, B = chain.information_blocks(self, st)
        try:
            _, _, logdet = chain.select_inverse(D, B)
        except np.linalg.LinAlgError:     # singular to machine precision: no Laplace value (NaN, as a negative
            logdet = np.nan               # determinant gives), so no candidate is supported on its strength
        return {"motion": float(lm), "observation": float(np.sum(t["log_density"][self.obs_mask])),
                "pose_constant": 1.5 * self.lay.n_poses * np.log(2 * np.pi), "half_log_det": 0.5 * float(logdet)}

    def log_likelihood(self, st: AState) -> float:
        """Laplace log p(O | model): data densities at the pose mode minus half log det of the pose information."""
        t = self.log_likelihood_terms(st)
        return float(t["motion"] + t["observation"] + t["pose_constant"] - t["half_log_det"])


def estimate_noise(problem: EffectProblem, st: AState, model: Model, seed: int = 0) -> tuple[Model, np.ndarray]:
    """Noise levels (as :func:`methods.graph.estimate_noise`) and the noise-only effect parameters."""
    A, e, groups = problem.jacobian(st)
    # the chain's own elimination: linear in the poses (SuperLU's minimum-degree order is not: 12x the time
    # for a four times longer log); a singular chain falls back to the sparse LU
    traces = noisemod.hat_traces(A, groups, seed=seed, lu=chain.arrow_solver(A, problem.lay.n_poses))
    wsum = {"reading": float(np.sum(problem.weight[problem.r_idx])),
            "bearing": float(np.sum(problem.weight[problem.b_idx]))}
    new = noisemod.group_scales(e, groups, traces, counts=wsum)
    m = model.with_(motion_noise=np.asarray(model.motion_noise, float) * [new["forward"], new["lateral"], new["turn"]],
                    reading_sigma=model.reading_sigma * new["reading"],
                    bearing_sigma=model.bearing_sigma * new["bearing"])
    theta = st.theta.copy()
    t = problem.observation_terms(st)
    for eff, s in problem.sensor_effects:
        if eff.noise_only:
            k = problem.obs_mask                       # hidden (held-out) observations do not count
            z_r = t["reading"][k] / (m.reading_sigma * t["scale"][k])
            z_b = t["bearing"][k] / m.bearing_sigma
            ctx = {"weight": t["weight"][k], "reading_scale": t["scale"][k], "reading_sigma": m.reading_sigma,
                   "bearing_sigma": m.bearing_sigma}
            theta[s] = eff.estimate_noise(theta[s], z_r, z_b, t["distance"][k], ctx)
    return m, theta


def marginals(problem: EffectProblem, st: AState) -> tuple[np.ndarray, np.ndarray]:
    """Pose covariances (K, 3, 3) and the parameter covariance (n_theta, n_theta) at ``st``.

    The parameter block is the inverse Schur complement of the pose chain (the exact marginal of
    the Gaussian approximation); each pose's covariance adds the parameters' share to its
    conditional covariance from the chain.
    """
    D, B, F, gp, Htt, gt = problem.normal_equations(st)
    n = F.shape[2]
    Xs = chain._chain_solve(D, B, np.ascontiguousarray(F), 0.0)           # Hpp^-1 F
    Ff, Xf = F.reshape(-1, n), Xs.reshape(-1, n)
    cov_t = np.linalg.inv(Htt - Ff.T @ Xf)
    cond, _, _ = chain.select_inverse(D, B)
    cov_p = cond + np.einsum("kin,nm,kjm->kij", Xs, cov_t, Xs)
    return cov_p, cov_t
