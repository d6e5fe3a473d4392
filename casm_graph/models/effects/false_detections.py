"""false_detections: some observations belong to the wrong landmark or to nothing at all."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register


def inlier_weights(log_inlier: np.ndarray, log_outlier: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Each sighting's posterior probability of being a true detection, and its mixture log density, from
    its log density as a true sighting and as a false one (uniform over the readings and bearings)."""
    if fraction <= 0:
        return np.ones_like(log_inlier), log_inlier
    mix = np.logaddexp(np.log1p(-fraction) + log_inlier, np.log(fraction) + log_outlier)
    return np.exp(np.log1p(-fraction) + log_inlier - mix), mix


def outlier_density(reading: np.ndarray, bearing: np.ndarray, reading_span: float) -> np.ndarray:
    """Log density of a false sighting: uniform over the span of readings and over all bearings (0 where
    a component was not measured)."""
    return (np.where(np.isfinite(reading), -np.log(reading_span), 0.0)
            + np.where(np.isfinite(bearing), -np.log(2 * np.pi), 0.0))


def reading_span(readings: np.ndarray) -> float:
    """The span a false reading is drawn from: the measured readings' range (1 without any)."""
    finite = readings[np.isfinite(readings)]
    return float(np.ptp(finite)) if len(finite) else 1.0


def share(weight: np.ndarray) -> float:
    """The false-detection share the inlier weights imply (the mixture's EM update), kept within [1e-4, 0.5]."""
    return float(np.clip(np.mean(1.0 - weight), 1e-4, 0.5))


def mixture_terms(reading: np.ndarray, bearing: np.ndarray, reading_sigma, bearing_sigma: float, fraction: float,
                  span: float) -> dict:
    """Per sighting, from its reading and bearing residuals (NaN: not measured) and their sigmas: the Gaussian
    log density of both (``gaussian``), the mixture's (``log_density``) and the inlier ``weight``."""
    lr = np.where(np.isfinite(reading), -0.5 * (reading / reading_sigma) ** 2 - np.log(reading_sigma)
                  - 0.5 * np.log(2 * np.pi), 0.0)
    lb = np.where(np.isfinite(bearing), -0.5 * (bearing / bearing_sigma) ** 2 - np.log(bearing_sigma)
                  - 0.5 * np.log(2 * np.pi), 0.0)
    weight, lmix = inlier_weights(lr + lb, outlier_density(reading, bearing, span), fraction)
    return {"gaussian": lr + lb, "log_density": lmix, "weight": weight}


@register
class FalseDetections(Effect):
    name = "false_detections"
    scale_free = True
    channel = "sensor"
    params = ("fraction",)
    start = (0.01,)
    scale = (0.01,)
    noise_only = True
    explains = ()
    signature = "tails"
    distinguished_by = ("many sightings of each landmark: a false one follows no landmark, while ordinary noise "
                        "stays near the sensor curve")
    physics = ("The vision system sometimes reports a beacon that is not there or names the wrong one "
               "(a similar colour in the background): a share of sightings follows no landmark.")

    def outlier_fraction(self, theta):
        return float(np.clip(theta[0], 0.0, 0.5))

    def estimate_noise(self, theta, reading_z, bearing_z, distance, ctx):
        return np.array([share(ctx["weight"])])

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
