"""What every kind of log's marginal likelihood of the noise levels, log p(O | lambda), offers the posterior
sampler and the pipeline: the sampled noise levels, their sampling coordinates and the Laplace moments of what is
integrated out (one subclass per kind of action model, :mod:`casm_graph.analysis.likelihood`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOG2PI = float(np.log(2 * np.pi))
MOTION_NAMES = ("motion_noise_forward", "motion_noise_lateral", "motion_noise_turn")


def length_factors(problem, model) -> tuple[np.ndarray, float]:
    """Each segment's motion sigma over the model's noise levels (its length's share of the noise, per axis) and
    the log-det constant -sum log of them: motion rows whitened by these factors alone weigh a step twice the
    median's half as much, as the calibration's graph does, whatever noise levels are then tried."""
    factor = problem.motion_sigma / np.asarray(model.motion_noise, float)[None, :]
    return factor, -float(np.sum(np.log(factor)))


@dataclass
class NoiseParameter:
    """One sampled noise level: its name, where it lives, its value at the MAP and its bounds."""

    name: str
    kind: str            # "reading", "bearing", "motion", "effect"
    index: int           # motion axis, or the column in the effects' theta vector
    value: float
    lower: float = 0.0
    upper: float = np.inf


class NoiseLikelihood:
    """What the posterior sampler and the pipeline read of a marginal likelihood log p(O | lambda).

    ``params`` (the sampled noise levels), their ``names`` and values at the MAP ``x_map``; the
    sampler's coordinates (``coords``, ``natural``, ``in_support``); calling it gives
    log p(O | x) up to a constant; ``parameter_moments`` gives the Laplace mean shift and
    covariance of the integrated-out parameters at noise levels x. Each kind of graph (action
    table, continuous commands) has its own subclass; ``problem`` and ``state`` are its graph and MAP.
    """

    params: list
    names: list
    x_map: np.ndarray
    integrated_out: tuple = ()

    def set_aside(self) -> int:
        """Sightings left out as gross outliers (a wild reading must not set the noise levels)."""
        return 0

    def coords(self, x) -> np.ndarray:
        """Sampling coordinates: log of every sigma, effect parameters as they are."""
        x = np.asarray(x, float)
        lg = np.array([p.kind != "effect" for p in self.params])
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(lg, np.log(np.where(lg, x, 1.0)), x)

    def natural(self, u) -> np.ndarray:
        u = np.asarray(u, float)
        lg = np.array([p.kind != "effect" for p in self.params])
        return np.where(lg, np.exp(np.where(lg, u, 0.0)), u)

    def in_support(self, x) -> bool:
        return all((p.lower <= v if p.kind == "effect" else p.lower < v) and v < p.upper
                   for p, v in zip(self.params, np.asarray(x, float)))

    def __call__(self, x) -> float:
        raise NotImplementedError

    def parameter_moments(self, x) -> tuple[np.ndarray, np.ndarray]:
        """(Gauss-Newton shift from the MAP, Laplace covariance) of the integrated-out parameters at ``x``."""
        raise NotImplementedError

    def reading_distances(self) -> np.ndarray:
        """Distance of every reading the likelihood uses from the MAP trajectory (the report's sensor coverage)."""
        return self.problem.predictions(self.state)["distance"][self.problem.r_sel]
