"""What the graph needs of an action model: its parameters, the motion factor's rows, and the velocity a sighting
sees. One file per kind (``table``: discrete actions; ``command_poly``: continuous commands through a polynomial
map); :class:`casm_graph.graph.problem.Problem` takes any of them, so "table or continuous?" is answered here only."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from casm_graph.io.log import Log
from casm_graph.models.model import Model


def velocity_window(model: Model, effects) -> float:
    """Seconds before a sighting over which the sensor hooks' velocity is averaged: the value of the parameter an
    effect names as its ``velocity_window`` (a latency's delay), 0 without one."""
    return float(sum(abs(model.effects.get(e.name, {}).get(e.velocity_window, 0.0))
                     for e in effects if getattr(e, "velocity_window", "")))


def with_lag_memory(sigma: np.ndarray, held: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """``sigma`` (S, 3) widened by what an actuator lag's memory of the velocity before the log could move each
    segment: ``held`` (S,) its displacement per unit of velocity offset, up to the range of the model's
    ``velocities`` (n, 3) (that velocity is unknown: at rest, or settled at another command)."""
    spread = np.max(np.abs(velocities), axis=0)
    return np.sqrt(sigma ** 2 + (held[:, None] * spread[None, :]) ** 2)


def sighting_means(log: Log, rows: np.ndarray, window: float) -> np.ndarray:
    """(N, c) mean of the per-step ``rows`` (T, c) over the ``window`` seconds before each sighting, and at least
    over the step that ends at it: the displacement a delayed image missed, divided by the delay, when the
    velocity changes within the delay. Before the log's first pose the robot is taken at rest: an image taken
    before the log began shows where it began (the independent world's first sightings, turning at 1.6 rad/s,
    were 7-12 sigmas off when the first step's velocity was carried back before the start)."""
    step = np.clip(log.obs_step - 1, 0, log.steps - 1)
    out = np.asarray(rows, float)[step]
    tp = log.pose_times
    t1 = tp[log.obs_step]
    t0 = t1 - window
    wide = (window > log.dt[step]) | (t0 < tp[0])
    if window > 0 and wide.any():
        cum = np.vstack([np.zeros(rows.shape[1]), np.cumsum(rows * log.dt[:, None], axis=0)])
        for j in range(rows.shape[1]):       # interp holds cum at 0 before the first pose: at rest
            out[wide, j] = (np.interp(t1[wide], tp, cum[:, j]) - np.interp(t0[wide], tp, cum[:, j])) / window
    return out


@dataclass(frozen=True)
class NoiseRules:
    """What the noise step may assume of the motion noise of an action model's robot."""

    huber_efficiency: bool = True          # the sightings' Huber-weighted sums corrected by the weighting's efficiency
    lateral_at_most_forward: bool = False  # wheels do not slip sideways more than they slip forward
    floor: float = 0.0                     # m, rad per step: below this a level is numerical, not physical

    def apply(self, motion: np.ndarray) -> np.ndarray:
        """The (forward, lateral, turn) levels as these rules allow them."""
        m = np.asarray(motion, float).copy()
        if self.lateral_at_most_forward:
            m[1] = min(m[1], m[0])
        return np.maximum(m, self.floor)


class ActionPart:
    """The action model's side of one log's graph on a layout ``lay`` (pose knots, segments, ``obs_knot``).

    ``n`` parameters, held in the problem's parameter vector first (then the curve, then the effects'), as an
    array of ``shape``. ``motion_effects`` are the (effect, slice) pairs acting on velocity, ``ls_index`` the
    effect parameters least squares moves (the problem's).
    """

    name = ""
    noise_rules = NoiseRules()
    lead = 0.0                   # the share of a step's turn made before it moves (factors.command; a table's: 0)
    layout_type: type            # the layout a graph with this part has (its knots and segments)
    n: int
    shape: tuple

    def __init__(self, log: Log, model: Model, lay, motion_effects=(), ls_index=np.zeros(0, int), effects=()):
        self.log, self.lay = log, lay
        self.motion_effects, self.ls_index = list(motion_effects), np.asarray(ls_index, int)
        self.noise_rules = self.rules(model)

    @classmethod
    def rules(cls, model: Model) -> NoiseRules:
        """What the noise step may assume of ``model``'s robot (graph-em's M-step follows the same rules)."""
        return cls.noise_rules

    @classmethod
    def default_layout(cls, log: Log, model: Model):
        """The layout a graph of ``model`` on ``log`` takes when the caller gives none."""
        raise NotImplementedError

    def params(self, model: Model) -> np.ndarray:
        """The model's action parameters (array of ``shape``)."""
        return np.array(model.action.params, float).reshape(self.shape)

    def with_params(self, model: Model, x: np.ndarray, std: np.ndarray | None = None) -> Model:
        """``model`` with action parameters ``x`` (and their std when given)."""
        return model.with_action_params(np.ravel(x), None if std is None else np.ravel(std))

    def prior(self, model: Model) -> tuple[np.ndarray, np.ndarray]:
        """(mean, sigma) of the weak prior on the flattened parameters."""
        raise NotImplementedError

    def motion_sigma(self, model: Model, poses: np.ndarray | None) -> np.ndarray:
        """(S, 3) motion noise of every segment (``poses``: the knots, for noise that depends on place)."""
        raise NotImplementedError

    def motion(self, poses: np.ndarray, x: np.ndarray, theta: np.ndarray, jacobians: bool = True,
               parameters: bool = True):
        """Unwhitened motion residual (S, 3) and [Ha, Hb] (S, 3, 3), H over the parameters (S, 3, n) and over the
        effects' least-squares parameters (S, 3, len(ls_index)) or None (``parameters`` False: both None)."""
        raise NotImplementedError

    def sighting_velocity(self, poses: np.ndarray, x: np.ndarray, theta: np.ndarray, jacobian: bool = True):
        """(N, 3) body velocity each sighting's sensor hooks read (a latency's), and its derivative (N, 3, n) with
        respect to the parameters (effects aside; None unless ``jacobian``)."""
        raise NotImplementedError

    def step_velocities(self, poses: np.ndarray, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """(T, 3) body velocity of every step of the log under parameters ``x`` and the motion effects at ``theta``
        (``poses``: the knots, where place-dependent effects read): what the model runs open-loop."""
        raise NotImplementedError

    def motion_covariates(self, poses: np.ndarray, x: np.ndarray, theta: np.ndarray, command_change: float):
        """(t, covariates, commanded, span) of every segment for the residual channels: its start (s since the log
        began), the covariates this kind of action model has (speed, turn rate, time since the action changed,
        ...), the model's velocity on each axis (S, 3) and the seconds it covers. ``command_change``: the share of
        a command's range a jump must pass to count as a new action (continuous commands)."""
        raise NotImplementedError

    def motion_noise_step(self, model: Model, problem, e: np.ndarray, A, groups: dict, lu) -> Model:
        """``model`` with the parameters of a motion-noise effect the part places (regions of the floor)
        re-estimated from the whitened residual ``e`` of Jacobian ``A`` (rows ``groups``, solver ``lu``)."""
        return model

    def carry(self, model: Model) -> np.ndarray | None:
        """(N, 3) displacement in the knot's body frame from each sighting's knot to its own step, None when every
        sighting has its own knot."""
        return None
