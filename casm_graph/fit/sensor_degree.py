"""The sensor curve's degree and variable, chosen by the data when the asked ones are too stiff.

The paper's cubic in the distance follows an Aibo's beacon height over its field, but not every sensor:
an apparent size a / (d + b) over a distance range of 20:1 leaves a cubic pixels off, and the misfit then
reads as an effect (heavy tails as false detections, a trend as lens distortion). After a fit, the readings
against the fitted distances are regressed on polynomials in d and in 1/d (:mod:`factors.reading`) up to
``max_degree``; the curve with the lowest BIC is taken when it changes the curve materially (by more than
``MATERIAL`` of the reading sigma, RMS over the sighted distances), so a curve the asked one already
follows keeps it.
"""
from __future__ import annotations

import numpy as np

from factors.reading import BASES, curve, fit_curve

MATERIAL = 0.2           # share of the reading sigma the better curve must move by, RMS over the sightings
TAIL = 4.0               # readings further than this many robust sigmas off the fitted curve stay out


def choose_curve(distance: np.ndarray, reading: np.ndarray, poly: np.ndarray, sigma: float, max_degree: int,
                 basis: str = "distance") -> tuple[np.ndarray, str] | None:
    """(coefficients, basis) of a curve the data demand over the fitted one (else None).

    ``distance``/``reading``: the sightings with a reading, distances from the fitted poses; ``poly`` the
    fitted curve's coefficients (low order first) in ``basis``, ``sigma`` its reading noise. Degrees from 1
    to ``max_degree`` in each basis compete (the fitted curve's own degree and basis among them); nothing
    changes unless ``max_degree`` exceeds the fitted degree (``--max-sensor-degree`` at the asked degree
    keeps the asked curve).
    """
    degree = len(poly) - 1
    max_degree = min(max_degree, len(np.unique(reading)) - 1)     # a curve needs more distinct readings than terms
    if max_degree <= degree or len(reading) < 10 * (max_degree + 1):
        return None
    res = reading - curve(distance, poly, basis)
    keep = np.abs(res) < TAIL * 1.4826 * np.median(np.abs(res))
    d, r = distance[keep], reading[keep]
    n = len(r)
    fits = {}
    for b in BASES:
        for k in range(1 if b != basis else degree, max_degree + 1):
            c = fit_curve(d, r, k, b)
            rss = float(np.sum((r - curve(d, c, b)) ** 2))
            fits[(b, k)] = (n * np.log(max(rss, 1e-300) / n) + (k + 1) * np.log(n), c)
    best = min(fits, key=lambda key: fits[key][0])
    if best == (basis, degree):
        return None
    moved = curve(d, fits[best][1], best[0]) - curve(d, poly, basis)
    return (fits[best][1], best[0]) if np.sqrt(np.mean(moved ** 2)) > MATERIAL * sigma else None
