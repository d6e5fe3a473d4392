"""false_detections: some observations belong to the wrong landmark or to nothing at all."""
from __future__ import annotations

import numpy as np

from .base import Effect, register


@register
class FalseDetections(Effect):
    name = "false_detections"
    channel = "sensor"
    params = ("fraction",)
    start = (0.01,)
    scale = (0.01,)
    noise_only = True
    explains = ()
    physics = ("The vision system sometimes reports a beacon that is not there or names the wrong one "
               "(a similar colour in the background): a share of sightings follows no landmark.")

    def outlier_fraction(self, theta):
        return float(np.clip(theta[0], 0.0, 0.5))

    def estimate_noise(self, theta, reading_z, bearing_z, distance, ctx):
        return np.array([float(np.clip(np.mean(1.0 - ctx["weight"]), 1e-4, 0.5))])

    def corrupt(self, theta, obs, rng):
        n = len(obs["landmark"])
        bad = rng.random(n) < theta[0]
        relabel = bad & (rng.random(n) < 0.5)
        junk = bad & ~relabel
        n_lm = obs["n_landmarks"]
        obs["landmark"] = np.where(relabel, (obs["landmark"] + rng.integers(1, n_lm, n)) % n_lm,
                                   obs["landmark"])
        lo, hi = np.nanmin(obs["reading"]), np.nanmax(obs["reading"])
        obs["reading"] = np.where(junk, rng.uniform(lo, hi, n), obs["reading"])
        obs["bearing"] = np.where(junk, rng.uniform(-np.pi, np.pi, n), obs["bearing"])
        return obs
