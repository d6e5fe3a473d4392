"""The sensor polynomial's degree, chosen by the data when the asked one is too stiff.

The paper's cubic follows an Aibo's beacon height over its field, but not every sensor: an apparent size
a / (d + b) over a distance range of 20:1 leaves a cubic pixels off, and the misfit then reads as an
effect (heavy tails as false detections, a trend as lens distortion). After a fit, the readings against
the fitted distances are regressed on polynomials up to ``max_degree``; the degree with the lowest BIC is
taken when it changes the curve materially (by more than ``MATERIAL`` of the reading sigma, RMS over the
sighted distances), so a curve the asked degree already follows keeps it.
"""
from __future__ import annotations

import numpy as np

MATERIAL = 0.2           # share of the reading sigma the better curve must move by, RMS over the sightings
TAIL = 4.0               # readings further than this many robust sigmas off the fitted curve stay out


def choose_degree(distance: np.ndarray, reading: np.ndarray, poly: np.ndarray, sigma: float,
                  max_degree: int) -> np.ndarray | None:
    """Coefficients of a higher-degree curve when the data demand one (else None).

    ``distance``/``reading``: the sightings with a reading, distances from the fitted poses; ``poly`` the
    fitted curve's coefficients (low order first), ``sigma`` its reading noise.
    """
    degree = len(poly) - 1
    max_degree = min(max_degree, len(np.unique(reading)) - 1)     # a curve needs more distinct readings than terms
    if max_degree <= degree or len(reading) < 10 * (max_degree + 1):
        return None
    res = reading - np.polynomial.polynomial.polyval(distance, poly)
    keep = np.abs(res) < TAIL * 1.4826 * np.median(np.abs(res))
    d, r = distance[keep], reading[keep]
    n = len(r)
    fits = {}
    for k in range(degree, max_degree + 1):
        c = np.polynomial.polynomial.polyfit(d, r, k)
        rss = float(np.sum((r - np.polynomial.polynomial.polyval(d, c)) ** 2))
        fits[k] = (n * np.log(max(rss, 1e-300) / n) + (k + 1) * np.log(n), c)
    best = min(fits, key=lambda k: fits[k][0])
    if best == degree:
        return None
    moved = np.polynomial.polynomial.polyval(d, fits[best][1]) - np.polynomial.polynomial.polyval(d, poly)
    return fits[best][1] if np.sqrt(np.mean(moved ** 2)) > MATERIAL * sigma else None
