"""One robust loss for sightings, used by every stage: Huber weights, a gate, a robust scale and a robust curve fit.

A single wild reading must not drag a least-squares step: whitened sighting residuals count
quadratically up to ``HUBER`` sigmas and linearly beyond (iteratively reweighted), residuals beyond
``GATE`` sigmas are set aside from the noise estimates, and the sensor curve's
first fit is a Huber regression (scipy's ``least_squares`` with ``loss="huber"``) at a scale taken
from the median absolute deviation.
"""
from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from factors.reading import curve, features, fit_curve

HUBER = 2.0          # sigmas: quadratic inside, linear beyond
GATE = 5.0           # sigmas: beyond this a sighting is set aside from noise estimates
# E[min(z^2, HUBER |z|)] for a standard normal z, which works out to P(|z| <= HUBER): the Huber-weighted sum
# of squares of Gaussian residuals is this fraction of the plain one, so noise estimates from it divide by it.
HUBER_EFFICIENCY = float(2 * stats.norm.cdf(HUBER) - 1)


def huber(e: np.ndarray, k: float = HUBER) -> np.ndarray:
    """Square-root weights that turn whitened residuals into Huber's (linear beyond ``k`` sigmas)."""
    a = np.abs(e)
    return np.sqrt(np.where(a > k, k / np.maximum(a, 1e-300), 1.0))


def huber_loss(e: np.ndarray, k: float = HUBER) -> np.ndarray:
    """Huber's rho of whitened residuals (GTSAM's ``mEstimator.Huber``): e^2 / 2 inside ``k``, k |e| - k^2 / 2 beyond.

    The rows weighted by :func:`huber` give the gradient of the sum of these (IRLS), which is what a
    least-squares step that reports this cost must use."""
    a = np.abs(e)
    m = np.minimum(a, k)
    return m * (a - 0.5 * m)


def mad_scale(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation of the finite entries (the Gaussian sigma, outliers aside)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not len(x):
        return 1.0
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) or 1.0


def polyfit(x: np.ndarray, y: np.ndarray, degree: int, basis: str = "distance") -> np.ndarray:
    """Sensor-curve coefficients (lowest power first, powers of ``x`` or of 1/x as ``basis`` says,
    :mod:`factors.reading`) of a Huber regression of ``y`` on ``x``.

    Starts from the least-squares fit of the points within the gate of a median-centred scale, so a
    reading thousands of times off has no say in the start either."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    keep = np.abs(y - np.median(y)) <= GATE * 3 * mad_scale(y) + 1e-12
    if keep.sum() <= degree:
        keep = np.ones(len(y), bool)
    c0 = fit_curve(x[keep], y[keep], degree, basis)
    scale = mad_scale(y[keep] - curve(x[keep], c0, basis))
    V = np.vander(x, degree + 1, increasing=True) if basis == "distance" else features(x, degree + 1, basis)[0]
    res = least_squares(lambda c: V @ c - y, c0, jac=lambda c: V, loss="huber", f_scale=HUBER * scale,
                        x_scale="jac", method="trf")
    return res.x
