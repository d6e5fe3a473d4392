"""Gross outliers: sightings no Gaussian noise model explains, pruned once as the paper does.

EKFS-EM discards first-iteration observations whose innovation is too unlikely. The graph prunes
once, after its coarse stage: each sighting's reading and bearing residuals, whitened by a robust
(median absolute deviation) scale so the outliers cannot inflate it, give a chi-square with one
or two degrees of freedom; a sighting beyond its 1 - 1e-5 quantile is dropped whole (reading and
bearing together: a false detection is false in both). On a clean log that drops almost nothing
(about one sighting in 100,000); a few percent of false detections otherwise drag the cubic
sensor curve into a wrong minimum.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from casm_graph.fit.residuals import observation
from casm_graph.graph.augmented import parameter_slices, theta_from_model
from casm_graph.graph.robust import mad_scale
from casm_graph.io.log import Log
from casm_graph.models.model import Model

TAIL = 1e-5


def outlying(log: Log, model: Model, poses: np.ndarray, tail: float = TAIL) -> np.ndarray:
    """Boolean mask of sightings whose whitened squared residual exceeds chi-square's ``1 - tail`` quantile."""
    r, b = observation(poses[log.obs_step], log, model)
    zr, zb = r / mad_scale(r), b / mad_scale(b)
    m2 = np.nan_to_num(zr ** 2) + np.nan_to_num(zb ** 2)
    dof = np.isfinite(zr).astype(int) + np.isfinite(zb).astype(int)
    limit = chi2.isf(tail, np.maximum(dof, 1))
    return (dof > 0) & (m2 > limit)


def kept(log: Log, model: Model, poses: np.ndarray, effects: list) -> np.ndarray:
    """The sightings a Gaussian likelihood should score: all but the gross outliers at ``poses`` (one reading
    thousands of sigmas off would otherwise set the noise levels, or pass for an effect), or all of them when
    ``effects`` (instances) include an outlier mixture such as ``false_detections``, which models them."""
    theta = theta_from_model(effects, model)
    if any(e.outlier_fraction(theta[s]) > 0 for e, s in zip(effects, parameter_slices(effects))):
        return np.ones(len(log.obs_t), bool)
    return ~outlying(log, model, np.asarray(poses, float))


def prune(log: Log, mask: np.ndarray) -> Log:
    """``log`` with the masked sightings marked not measured (kept in place, so indices still match)."""
    return replace(log, obs_reading=np.where(mask, np.nan, log.obs_reading),
                   obs_bearing=np.where(mask, np.nan, log.obs_bearing))


def set_aside(log: Log, model: Model, poses: np.ndarray) -> tuple[Log, np.ndarray]:
    """``log`` with its gross outliers at ``model`` and ``poses`` (:func:`outlying`) marked not measured, and the
    mask of them: what every method does before a fit whose likelihood is Gaussian."""
    mask = outlying(log, model, poses)
    return prune(log, mask), mask
