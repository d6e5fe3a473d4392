"""Discrete actions: one (vx, vy, w) row per action id, the paper's velocity table.

Segments run one action each (knots at every change); the motion effects' hooks see the segment's row,
the row before the action changed, and the segment's start pose, and chain their derivatives
(:mod:`factors.effect_motion`). On a coarse layout a sighting a few steps from its knot is seen from the
knot's pose carried there by the table's velocity (held at the problem's start, like the noise levels).
"""
from __future__ import annotations

import numpy as np

import factors
from casm_graph.graph import table as G
from casm_graph.graph.augmented import motion_function
from casm_graph.graph.actions.base import ActionPart, NoiseRules, sighting_means, velocity_window, with_lag_memory
from casm_graph.models.effects.actuator_lag import ActuatorLag
from casm_graph.models.model import Model


class TableActions(ActionPart):
    """The velocity table's rows in a graph on a :class:`casm_graph.graph.table.Layout`."""

    name = "table"
    layout_type = G.Layout
    # a level below 1e-4 m or rad per step is numerical: on a two-minute fleet log the forward level fell by a
    # factor 7-50 at each noise step of a diagnosis's candidate rounds until the information matrix was singular
    noise_rules = NoiseRules(floor=1e-4)

    def __init__(self, log, model: Model, lay, motion_effects=(), ls_index=np.zeros(0, int), effects=()):
        super().__init__(log, model, lay, motion_effects, ls_index, effects)
        self.A = lay.n_actions
        self.n, self.shape = 3 * self.A, (self.A, 3)
        if len(effects) and np.any(lay.seg_steps != 1):
            raise ValueError("effects act step by step: their graph needs a pose at every step")
        act = lay.seg_action
        change = np.concatenate([[True], act[1:] != act[:-1]])
        start_idx = np.maximum.accumulate(np.where(change, np.arange(len(act)), 0))
        self.prev_row = np.where(start_idx > 0, act[np.maximum(start_idx - 1, 0)], act)
        t_rel = log.t[lay.knots[:-1]] - log.t[0]
        self.m_ctx = {"t": t_rel, "since": t_rel - t_rel[start_idx], "dt": lay.seg_dt * lay.seg_steps}
        self.window = velocity_window(model, effects)
        self._window_dv = None

    @classmethod
    def default_layout(cls, log, model: Model) -> G.Layout:
        """A pose at every step."""
        return G.layout(log, model, stride=1)

    def prior(self, model: Model) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(self.n), np.full(self.n, G.VELOCITY_PRIOR_SIGMA)

    def motion_sigma(self, model: Model, poses=None) -> np.ndarray:
        """The levels per step of the log's median length, grown with the segment's time (a random walk): a log
        whose steps vary in length (a real robot's odometry with gaps) trusts a one-second step less. With an
        actuator lag, the velocity it held before the log is unknown (at rest, or settled at another action; the
        graph takes it settled at the first), up to the table's velocity range: the first segments trust less what
        the lag's memory of it could move them (as on continuous commands)."""
        steps = self.log.in_median_steps(self.lay.seg_steps * self.lay.seg_dt)
        sigma = np.asarray(model.motion_noise, float)[None, :] * np.sqrt(steps)[:, None]
        lag = model.effects.get(ActuatorLag.name)
        if lag and abs(lag.get("tau", 0.0)) > 0:
            held = np.add.reduceat(ActuatorLag.start_memory(lag, self.log.dt), self.lay.knots[:-1])
            sigma = with_lag_memory(sigma, held, np.asarray(model.velocities))
        return sigma

    def _fn(self, theta):
        return motion_function(self.motion_effects, self.m_ctx, theta)

    def step_velocity(self, poses: np.ndarray, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(S, 3) velocity each segment runs under the table and the motion effects."""
        V = np.asarray(x).reshape(self.shape)
        return factors.effect_motion.velocity(self._fn(theta), V[self.lay.seg_action], V[self.prev_row], poses[:-1])

    def step_velocities(self, poses, x, theta):
        return np.repeat(self.step_velocity(poses, x, theta), self.lay.seg_steps, axis=0)

    def motion_covariates(self, poses, x, theta, command_change):
        lay = self.lay
        v = self.step_velocity(poses, x, theta)
        cov = {"speed": np.hypot(v[:, 0], v[:, 1]), "turn_rate": v[:, 2], "time_since_action_change": self.m_ctx["since"],
               "action": self.log.action[lay.knots[:-1]].astype(float)}
        return self.m_ctx["t"], cov, np.asarray(x).reshape(self.shape)[lay.seg_action], lay.seg_steps * lay.seg_dt

    def motion(self, poses, x, theta, jacobians=True, parameters=True):
        lay, V = self.lay, np.asarray(x).reshape(self.shape)
        if self.motion_effects:
            e, (Ha, Hb, _), dv = factors.effect_motion.error(
                self._fn(theta), poses, V, lay.seg_action, self.prev_row, self.log.dt, theta, self.ls_index,
                [s for _, s in self.motion_effects])
            own, prev, Ha, d_theta = dv["own"], dv["prev"], Ha + dv["pose"], dv["theta"]
        else:
            e, (Ha, Hb, own) = factors.action.error(poses[:-1], poses[1:], V[lay.seg_action], lay.seg_steps,
                                                    lay.seg_dt)
            prev, d_theta = None, None
        if not (jacobians and parameters):
            return e, [Ha, Hb], None, None
        S = len(e)
        Hx = np.zeros((S, 3, self.n))
        rows = np.arange(S)
        for c in range(3):                 # one row per step in each statement: no repeated index, no add.at
            Hx[rows, :, 3 * lay.seg_action + c] += own[:, :, c]
            if prev is not None:
                Hx[rows, :, 3 * self.prev_row + c] += prev[:, :, c]
        return e, [Ha, Hb], Hx, d_theta

    def window_dv(self) -> np.ndarray:
        """(N, 3, n): each sighting's share of every action over the velocity window, its velocity's derivative
        (built when first asked: dense in the actions, too large on a graph whose every step is an action)."""
        if self._window_dv is None:
            lay = self.lay
            share = sighting_means(self.log, np.eye(self.A)[np.repeat(lay.seg_action, lay.seg_steps)], self.window)
            self._window_dv = np.zeros((len(self.log.obs_t), 3, self.n))
            for c in range(3):
                self._window_dv[:, c, c::3] = share
        return self._window_dv

    def sighting_velocity(self, poses, x, theta, jacobian=True):
        """The velocity of the step before each sighting, or with a velocity window (a latency's delay) the mean
        over the window, which spans an action change when one falls within it; the derivative is the table rows'
        (effects aside)."""
        v = self.step_velocity(poses, x, theta)
        if self.window > 0:
            v = sighting_means(self.log, np.repeat(v, self.lay.seg_steps, axis=0), self.window)
            return v, (self.window_dv() if jacobian else None)
        step = np.clip(self.log.obs_step - 1, 0, len(v) - 1)
        if not jacobian:
            return v[step], None
        row = self.lay.seg_action[step]
        dv = np.zeros((len(step), 3, self.n))
        for c in range(3):
            dv[np.arange(len(step)), c, 3 * row + c] = 1.0
        return v[step], dv

    def carry(self, model: Model) -> np.ndarray | None:
        lay = self.lay
        shift = self.log.obs_step - lay.knots[lay.obs_knot]
        if not np.any(shift):
            return None
        seg = np.clip(np.where(shift >= 0, lay.obs_knot, lay.obs_knot - 1), 0, lay.n_poses - 2)
        sign = np.where(shift < 0, -1.0, 1.0)
        v = np.asarray(model.velocities, float)[lay.seg_action[seg]] * sign[:, None]
        return factors.action.displacement(v, np.abs(shift), lay.seg_dt[seg])[0]
