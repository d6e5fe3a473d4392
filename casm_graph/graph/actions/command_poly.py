"""Continuous commands: forward and turn velocity (and sideways, for ``vx, vy, w``) as polynomials of the
commands (:mod:`casm_graph.models.command_model`), their coefficients the parameters.

Knots every ``knot_dt`` seconds and at every sighting's step; consecutive knots are joined by one
:mod:`factors.command` factor over the command steps between them (padded to a common length). Motion
effects act on every step's velocity, their derivatives central differences of the vectorised
forward pass (few parameters). A latency's velocity is the map's mean over the delay before the
sighting. regional_motion_noise sets each segment's forward and turn sigmas from the region its
start knot is in.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

import factors
from casm_graph.graph import noise
from casm_graph.graph.actions.base import ActionPart, NoiseRules, sighting_means, velocity_window, with_lag_memory
from casm_graph.graph.augmented import motion_function
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects import regional_motion_noise as RMN
from casm_graph.models.model import Model

DEFAULT_KNOT_DT = 0.25       # s between knots when the caller gives no layout (the fine graph's)
COMMAND_CHANGE = 0.1         # a command jump of this share of its range starts an "action" (the residuals' covariate)
PARAM_PRIOR_REL = 2.0        # command-map prior: centred on the nominal map (velocity = command), std twice the
                             # command scale


@dataclass(frozen=True)
class Layout:
    """Pose knots and the command steps (padded to a common length) between consecutive knots."""

    knots: np.ndarray        # (K,) pose-step index of each knot
    seg_idx: np.ndarray      # (K-1, kmax) command step of each slot (0 in padding)
    seg_dt: np.ndarray       # (K-1, kmax) step length (0 in padding)
    obs_knot: np.ndarray     # (N,) knot of each observation

    @property
    def n_poses(self) -> int:
        return len(self.knots)

    @property
    def seg_time(self) -> np.ndarray:
        return self.seg_dt.sum(axis=1)


def layout(log: Log, knot_dt: float) -> Layout:
    """Knots every ``knot_dt`` seconds, at every observation's step, and at the first and last pose."""
    tp = log.pose_times
    T = log.steps
    regular = np.searchsorted(tp, np.arange(tp[0], tp[-1], knot_dt))
    knots = np.unique(np.concatenate([regular, log.obs_step, [0, T]])).astype(int)
    n = np.diff(knots)
    kmax = int(n.max())
    slot = np.arange(kmax)[None, :]
    mask = slot < n[:, None]
    idx = np.where(mask, knots[:-1, None] + slot, 0)
    dt = np.where(mask, log.dt[idx], 0.0)
    return Layout(knots, idx, dt, np.searchsorted(knots, log.obs_step))


def time_since_command_change(log: Log, frac: float = COMMAND_CHANGE) -> np.ndarray:
    """(T,) seconds since either command last jumped by more than ``frac`` of its range."""
    span = np.ptp(log.controls, axis=0)
    jump = np.any(np.abs(np.diff(log.controls, axis=0)) > frac * np.where(span > 0, span, 1.0), axis=1)
    last = np.maximum.accumulate(np.where(np.concatenate([[True], jump]), np.arange(log.steps), 0))
    return log.t - log.t[last]


def command_acceleration(seg_v: np.ndarray, seg_mid: np.ndarray) -> np.ndarray:
    """(S, 3) rate of change of the model's velocity into each segment from the one before (0 for the first):
    with smooth commands, where ``time_since_action_change`` says little, a delay (an actuator lag, or a camera
    latency the smoothed poses take in) leaves motion residuals of about minus the delay times this. Backward,
    so that a robot steering by feedback, whose later commands answer its present motion noise, shows none."""
    out = np.zeros_like(seg_v)
    if len(seg_mid) > 1:
        out[1:] = np.diff(seg_v, axis=0) / np.maximum(np.diff(seg_mid), 1e-9)[:, None]
    return out


class CommandPoly(ActionPart):
    """The command map's coefficients in a graph on a :class:`Layout`."""

    name = "command_poly"
    layout_type = Layout
    # the sightings beyond the gate are already out of the problem; the Huber-weighted sums are taken as they are
    # (the table graph's efficiency correction moved MRCLAM robot 1's fit: BENCHMARKS.md, bad data). A floor of
    # 1e-4 m or rad per step: a robot that never slips sideways drove the lateral level to 1e-13, and the
    # information matrix singular.
    noise_rules = NoiseRules(huber_efficiency=False, lateral_at_most_forward=True, floor=1e-4)
    #   (an omnidirectional robot, commanded sideways, may slip sideways more than forward)

    @classmethod
    def rules(cls, model: Model) -> NoiseRules:
        """An omnidirectional robot, commanded sideways, may slip sideways more than forward."""
        return replace(cls.noise_rules, lateral_at_most_forward=False) if model.command.sizes[1] else cls.noise_rules

    def __init__(self, log, model: Model, lay: Layout, motion_effects=(), ls_index=np.zeros(0, int), effects=()):
        super().__init__(log, model, lay, motion_effects, ls_index, effects)
        cm = model.command
        bv, by, bw = cm.basis(log.controls, log.dt)
        self.Bv, self.By, self.Bw = bv[lay.seg_idx], by[lay.seg_idx], bw[lay.seg_idx]
        self.nv, self.ny = bv.shape[1], by.shape[1]
        self.lead = cm.lead
        self.n = len(cm.params)
        self.shape = (self.n,)
        self.seg_region = None
        if self.motion_effects:          # step context, one row per slot of the padded segments
            c = log.controls
            change = np.concatenate([[True], np.any(c[1:] != c[:-1], axis=1)])
            run0 = np.maximum.accumulate(np.where(change, np.arange(len(c)), 0))
            prev = np.maximum(run0 - 1, 0)
            t0 = log.pose_times[:-1] - log.pose_times[0]
            idx = lay.seg_idx
            self.m_ctx = {"t": t0[idx].ravel(), "since": (t0 - t0[run0])[idx].ravel(),
                          "dt": np.where(lay.seg_dt > 0, lay.seg_dt, float(np.median(log.dt))).ravel()}
            self.Bv_prev, self.By_prev, self.Bw_prev = bv[prev][idx], by[prev][idx], bw[prev][idx]
        every = sighting_means(log, np.hstack([bv, by, bw]), velocity_window(model, effects))
        self.Bv_obs, self.By_obs, self.Bw_obs = (every[:, :self.nv], every[:, self.nv:self.nv + self.ny],
                                                 every[:, self.nv + self.ny:])

    @classmethod
    def default_layout(cls, log, model: Model) -> Layout:
        """Knots every ``DEFAULT_KNOT_DT`` seconds and at every sighting's step."""
        return layout(log, DEFAULT_KNOT_DT)

    def prior(self, model: Model) -> tuple[np.ndarray, np.ndarray]:
        cm = model.command
        nominal = cm.same_form(self.log.controls)
        return nominal.params, PARAM_PRIOR_REL * np.concatenate([np.full(sl.stop - sl.start, cm.scale[col])
                                                                 for _, col, _, sl in cm.maps])

    def motion_sigma(self, model: Model, poses: np.ndarray | None) -> np.ndarray:
        lay, log = self.lay, self.log
        steps = log.in_median_steps(np.maximum(lay.seg_time, 1e-9))
        sigma = np.asarray(model.motion_noise, float)[None, :] * np.sqrt(steps)[:, None]
        if RMN.RegionalMotionNoise.name in model.effects:
            if poses is None:
                raise ValueError("regional_motion_noise: the problem needs the knot poses to place its segments")
            regions, k = RMN.from_entry(model.effects[RMN.RegionalMotionNoise.name])
            self.seg_region = regions.of(np.asarray(poses)[:-1, :2])
            v = model.command.velocities(log.controls, log.dt)[lay.seg_idx]
            self.seg_r = np.sum(np.abs(v[..., 0]) * lay.seg_dt, axis=1)
            self.seg_turn = np.sum(np.abs(v[..., 2]) * lay.seg_dt, axis=1)
            vr, vt = RMN.variances(k[self.seg_region], self.seg_r, self.seg_turn)
            sigma[:, 0], sigma[:, 2] = np.sqrt(vr), np.sqrt(vt)
        cm = model.command
        if cm.lag > 0:
            held = np.sum(cm.lag_memory(log.dt)[lay.seg_idx] * (lay.seg_dt > 0), axis=1)
            sigma = with_lag_memory(sigma, held, cm.velocities(log.controls))
        return sigma

    def motion_noise_step(self, model: Model, problem, e: np.ndarray, A, groups: dict, lu) -> Model:
        """regional_motion_noise's (k_r, k_t, k_d) of each region refitted by maximum likelihood to its segments'
        expected squared forward and turn errors, an EM step: E[eps^2] = sigma^2 (w^2 + h), w the whitened
        residual and h the leverage of its row (the hat matrix's diagonal, exact). A region with fewer than
        ``MIN_SEGMENTS`` segments keeps its k's and is recorded as undetermined (its count)."""
        if self.seg_region is None:
            return model
        regions, k = RMN.from_entry(model.effects[RMN.RegionalMotionNoise.name])
        n = len(self.seg_region)
        w = e[:3 * n].reshape(-1, 3)
        h = np.clip(noise.leverages(A, np.concatenate([groups["forward"], groups["turn"]]), lu=lu).reshape(2, n).T,
                    0.0, 1.0)
        e2 = problem.motion_sigma[:, [0, 2]] ** 2 * (w[:, [0, 2]] ** 2 + h)
        k_new = k.copy()
        for g in range(regions.count):
            sel = self.seg_region == g
            if sel.sum() >= RMN.MIN_SEGMENTS:
                k_new[g] = RMN.estimate(self.seg_r[sel], self.seg_turn[sel], e2[sel, 0], e2[sel, 1], k[g])
        counts = np.bincount(self.seg_region, minlength=regions.count)
        return model.with_(effects={**model.effects, RMN.RegionalMotionNoise.name: RMN.entry(regions, k_new, counts)})

    def motion_covariates(self, poses, x, theta, command_change):
        lay, log = self.lay, self.log
        v = self._velocities(np.asarray(x, float), self.Bv, self.By, self.Bw)
        seg_v = np.sum(v * lay.seg_dt[..., None], axis=1) / np.maximum(lay.seg_time, 1e-9)[:, None]
        t = log.pose_times[lay.knots[:-1]] - log.t[0]
        accel = command_acceleration(seg_v, t + 0.5 * lay.seg_time)
        cov = {"speed": seg_v[:, 0], "turn_rate": seg_v[:, 2],
               "time_since_action_change": time_since_command_change(log, command_change)[lay.knots[:-1]],
               "acceleration": accel[:, 0], "turn_acceleration": accel[:, 2]}
        return t, cov, seg_v, lay.seg_time

    def _velocities(self, p: np.ndarray, Bv: np.ndarray, By: np.ndarray, Bw: np.ndarray) -> np.ndarray:
        """(..., 3) body velocity of basis rows under map coefficients ``p`` (sideways 0 without a ``vy`` map)."""
        nv, ny = self.nv, self.ny
        v = Bv @ p[:nv]
        return np.stack([v, By @ p[nv:nv + ny] if ny else np.zeros_like(v), Bw @ p[nv + ny:self.n]], axis=-1)

    def _slot_velocities(self, p: np.ndarray, theta: np.ndarray, start: np.ndarray) -> np.ndarray:
        """(S, kmax, 3) velocity of every step of every segment under map ``p`` and the motion effects at
        ``theta``, each step's context pose placed along the segment by the map alone from its ``start`` pose."""
        v0 = self._velocities(p, self.Bv, self.By, self.Bw)
        if not self.motion_effects:
            return v0
        _, rel = factors.command.integrate(v0, self.lay.seg_dt, self.lead)
        c, s = np.cos(start[:, 2])[:, None], np.sin(start[:, 2])[:, None]
        pose = np.stack([start[:, 0:1] + c * rel[..., 0] - s * rel[..., 1],
                         start[:, 1:2] + s * rel[..., 0] + c * rel[..., 1], start[:, 2:3] + rel[..., 2]], axis=-1)
        fn = motion_function(self.motion_effects, self.m_ctx, theta)
        return fn(v0.reshape(-1, 3), self._velocities(p, self.Bv_prev, self.By_prev, self.Bw_prev).reshape(-1, 3),
                  pose.reshape(-1, 3)).reshape(v0.shape)

    def _segment_motion(self, p: np.ndarray, theta: np.ndarray, start: np.ndarray) -> np.ndarray:
        """(S, 3) displacement of every segment under map ``p`` and the motion effects at ``theta``."""
        return factors.command.integrate(self._slot_velocities(p, theta, start), self.lay.seg_dt, self.lead)[0]

    def step_velocities(self, poses, x, theta):
        v = self._slot_velocities(np.asarray(x, float), np.asarray(theta, float), np.asarray(poses)[:-1])
        out = np.zeros((self.log.steps, 3))
        slot = self.lay.seg_dt > 0
        out[self.lay.seg_idx[slot]] = v[slot]
        return out

    def motion(self, poses, x, theta, jacobians=True, parameters=True):
        P = poses
        if not self.motion_effects:
            e, (Ha, Hb, Hx) = factors.command.error(P[:-1], P[1:], x, self.Bv, self.Bw, self.lay.seg_dt, self.By,
                                                    self.lead)
            return e, [Ha, Hb], (Hx if parameters else None), None
        rel, Ha, Hb = factors.base.relative(P[:-1], P[1:])
        d = self._segment_motion(x, theta, P[:-1])
        e = np.column_stack([rel[:, :2] - d[:, :2], wrap(rel[:, 2] - d[:, 2])])
        if not jacobians:
            return e, [Ha, Hb], None, None
        h = factors.effect_motion.STEP
        for c in range(3):
            dp = (self._segment_motion(x, theta, factors.effect_motion.body_step(P[:-1], c, h))
                  - self._segment_motion(x, theta, factors.effect_motion.body_step(P[:-1], c, -h)))
            Ha[:, :, c] -= dp / (2 * h)
        if not parameters:
            return e, [Ha, Hb], None, None

        def column(p, th, arr, j):
            step = h * max(1.0, abs(arr[j]))
            arr[j] += step
            plus = self._segment_motion(p, th, P[:-1])
            arr[j] -= 2 * step
            minus = self._segment_motion(p, th, P[:-1])
            arr[j] += step
            return -(plus - minus) / (2 * step)

        p, th = np.array(x, float), np.array(theta, float)
        Hx = np.stack([column(p, th, p, j) for j in range(self.n)], axis=2)
        Ht = np.zeros((len(e), 3, len(self.ls_index)))
        for j, col in enumerate(self.ls_index):
            if any(s.start <= col < s.stop for _, s in self.motion_effects):
                Ht[:, :, j] = column(p, th, th, int(col))
        return e, [Ha, Hb], Hx, Ht

    def sighting_velocity(self, poses, x, theta, jacobian=True):
        nv, ny = self.nv, self.ny
        v = self._velocities(np.asarray(x, float), self.Bv_obs, self.By_obs, self.Bw_obs)
        if not jacobian:
            return v, None
        dv = np.zeros((len(v), 3, self.n))
        dv[:, 0, :nv], dv[:, 1, nv:nv + ny], dv[:, 2, nv + ny:] = self.Bv_obs, self.By_obs, self.Bw_obs
        return v, dv
