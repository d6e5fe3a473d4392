"""The sensor curve's degree and variable, chosen by the data when the asked ones are too stiff.

The paper's cubic in the distance follows an Aibo's beacon height over its field, but not every sensor:
an apparent size a / (d + b) over a distance range of 20:1 leaves a cubic pixels off, and the misfit then
reads as an effect (heavy tails as false detections, a trend as lens distortion). After a fit, the readings
against the fitted distances are regressed on polynomials in d and in 1/d (:mod:`factors.reading`) up to
``max_degree``; the curve with the lowest BIC is taken when it changes the curve materially (by more than
``SensorCurveOptions.material`` of the reading sigma, RMS over the sighted distances), so a curve the asked one already
follows keeps it. Material here is what the diagnosis calls material: a misfit of a tenth of the sigma is 1 %
of the reading residuals' variance, the share (``DiagnoseOptions.structure_omega2``) at which their structure
against the distance would be named ``unexplained:distance``.

That choice cannot find 1/d from a fit in d that went wrong near the landmarks (from the paper's flat start
a steep apparent size puts the robot almost on the landmark, and those distances favour d). So when a fit
in d shows the marks of it (:func:`suspect`), a second calibration starts with the curve in 1/d and the
two are scored on the sightings at least one of them explains, each under its own noise levels
(:func:`better_curve`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from casm_graph.fit.outliers import kept, prune
from casm_graph.fit.residuals import distances
from casm_graph.io.log import Log
from casm_graph.models.model import Model
from factors.reading import BASES, curve, fit_curve


@dataclass(frozen=True)
class SensorCurveOptions:
    """When the data move the sensor curve; recorded in model.json ``fit.options.graph.sensor_curve``."""

    material: float = 0.1          # share of the reading sigma the better curve must move by, RMS over the sightings
    #                                (1 % of the reading variance: what the diagnosis calls material structure)
    tail: float = 4.0              # readings further than this many robust sigmas off the fitted curve stay out
    suspect_pruned: float = 0.002  # share of the readings pruned beyond which a fit in d is tried against one in 1/d
    margin: float = 10.0           # the other curve's score must be higher by this (and BIC's penalty for extra terms)


DEFAULTS = SensorCurveOptions()


def near_curve(res: np.ndarray, tail: float) -> np.ndarray:
    """The readings whose residuals ``res`` off a curve lie within ``tail`` robust sigmas (1.4826 times their median
    absolute value): the ones a curve is regressed on."""
    return np.abs(res) < tail * 1.4826 * np.median(np.abs(res))


def choose_curve(distance: np.ndarray, reading: np.ndarray, poly: np.ndarray, sigma: float, max_degree: int,
                 basis: str = "distance", options: SensorCurveOptions = DEFAULTS) -> tuple[np.ndarray, str] | None:
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
    keep = near_curve(res, options.tail)
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
    return (fits[best][1], best[0]) if np.sqrt(np.mean(moved ** 2)) > options.material * sigma else None


def suspect(model: Model, log: Log, options: SensorCurveOptions = DEFAULTS) -> bool:
    """Whether a calibration shows the marks of a curve that misses near the landmarks: the data raised its
    degree, or it pruned (set aside, on continuous commands) more than ``options.suspect_pruned`` of the readings (a
    clean log prunes about 1 in 100,000)."""
    degree = model.fit.get("sensor_degree", {})
    n = int(np.sum(np.isfinite(log.obs_reading)))
    pruned = model.fit.get("outliers_pruned", (model.fit.get("outliers_set_aside") or {}).get("reading", 0))
    return n > 0 and (degree.get("fitted", 0) > degree.get("asked", 0) or pruned > options.suspect_pruned * n)


def better_curve(log: Log, first, other, score, options: SensorCurveOptions = DEFAULTS, effects=()):
    """``other`` (a fit with another sensor curve) when its score beats ``first``'s by more than ``options.margin``
    plus BIC's half log n per extra coefficient, and its curve differs materially (by more than ``options.material``
    of the reading sigma, RMS over the sightings); else ``first``. ``score(log, fit)`` is a fit's log-likelihood
    under its own noise levels (``effects``, instances, acting), taken on the sightings :func:`curve_scores`
    chooses. The choice is recorded in ``fit.sensor_degree`` (``tried``: each curve's score)."""
    scores = curve_scores(log, (first, other), score, effects)
    ok = np.isfinite(log.obs_reading)
    extra = len(other.model.reading_poly) - len(first.model.reading_poly)
    d = distances(other.poses[log.obs_step], log)[ok]
    moved = np.sqrt(np.mean((other.model.reading(d) - first.model.reading(d)) ** 2))
    take = (scores[1] - options.margin - 0.5 * extra * np.log(max(int(ok.sum()), 2)) > scores[0]
            and moved > options.material * min(first.model.reading_sigma, other.model.reading_sigma))
    keep = other if take else first
    tried = [{"basis": f.model.reading_basis, "degree": len(f.model.reading_poly) - 1, "score": round(float(c), 1)}
             for f, c in zip((first, other), scores)]
    keep.model.fit["sensor_degree"] = {**keep.model.fit.get("sensor_degree", {}), "tried": tried}
    return keep


def curve_scores(log: Log, fits, score, effects=()) -> tuple[float, ...]:
    """``score(log, fit)`` of each of ``fits`` on the sightings at least one of them explains (not a gross outlier
    at its fit, :func:`casm_graph.fit.outliers.kept`; all of them when ``effects`` model outliers): under Huber's
    loss a reading thousands of sigmas off every curve costs in proportion to its distance over the reading sigma,
    so one such reading had the curve with the larger sigma win (a floor with one reading times 10,000 took a
    quintic in 1/d), while near sightings only one curve follows are the evidence between them."""
    keep = np.logical_or.reduce([kept(log, f.model, f.poses, list(effects)) for f in fits])
    scored = prune(log, ~keep)
    return tuple(score(scored, f) for f in fits)
