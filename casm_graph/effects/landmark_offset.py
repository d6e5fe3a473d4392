"""landmark_offset: a landmark stands somewhere other than the map says."""
from __future__ import annotations

import numpy as np

from .base import Effect, register

PRIOR_SIGMA = 0.5   # m; also pins the gauge (moving every landmark and the path together changes nothing)


@register
class LandmarkOffset(Effect):
    name = "landmark_offset"
    channel = "sensor"
    params = ()
    start = ()
    scale = ()
    explains = (("reading", "landmark"), ("bearing", "landmark"), ("reading", "x"), ("reading", "y"),
                ("bearing", "x"), ("bearing", "y"))
    physics = ("The map is wrong about a landmark: it was knocked or measured carelessly, so sightings "
               "of it disagree with the others in both distance and direction.")

    def __init__(self, log=None):
        super().__init__(log)
        ids = log.landmark_ids if log is not None else np.arange(4)
        self.params = tuple(f"{ax}_{int(i)}" for i in ids for ax in ("dx", "dy"))
        self.start = tuple(0.0 for _ in self.params)
        self.scale = tuple(0.01 for _ in self.params)

    def free_parameters(self):
        return max(len(self.params) - 3, 0)

    def prior(self):
        return np.zeros(len(self.params)), np.full(len(self.params), PRIOR_SIGMA)

    def geometry(self, theta, pose, landmark_xy, ctx):
        off = np.asarray(theta).reshape(-1, 2)
        return pose, landmark_xy + off[ctx["landmark"]]

    def simulate_params(self, value, rng):
        n = len(self.params) // 2
        off = np.zeros((n, 2))
        which = int(rng.integers(n))
        ang = rng.uniform(-np.pi, np.pi)
        off[which] = value * np.array([np.cos(ang), np.sin(ang)])
        return off.ravel()

    def describe(self, theta):
        return {p: float(v) for p, v in zip(self.params, theta)}
