"""Marginal likelihood of the noise levels, log p(O | lambda), with the trajectory and the parameters integrated out.

lambda is every noise level of a model: the reading and bearing sigmas, the per-step motion noise
(forward, lateral, turn) and the parameters of the noise-only effects (e.g. the growth of
``range_dependent_noise``, the ``false_detections`` fraction). Everything else, the poses, the action
model, the sensor polynomial and the effects' least-squares parameters, is integrated out by a Laplace
approximation on the factor graph with the linearisation held at the MAP: the whitened Jacobian then
depends on lambda only through row weights, and

    log p(O | lambda) = sum_rows log p(e0_row; lambda) + 1/2 g' H^-1 g - 1/2 log det H + const,

with e0 the residuals at the MAP, H = J' W J + prior and g = J' W e0 (the Gauss-Newton step
from the MAP under the new weights). This is exact for the linearised model, so it differs from
the filter's p(O | lambda) only by the linearisation (test_uncertainty.py checks the two agree).

One part per kind of action model, one file each, by the model's ``action.kind``: ``table``
(:mod:`.table`) and ``command_poly`` (:mod:`.command_poly`); :class:`.base.NoiseLikelihood` is what
they share.
"""
from __future__ import annotations

import numpy as np

from casm_graph.analysis.likelihood.base import NoiseLikelihood, NoiseParameter
from casm_graph.analysis.likelihood.command_poly import ContinuousMarginalLikelihood, continuous_likelihood
from casm_graph.analysis.likelihood.table import MarginalLikelihood, likelihood
from casm_graph.io.log import Log
from casm_graph.models.model import Model

__all__ = ["NoiseLikelihood", "NoiseParameter", "MarginalLikelihood", "ContinuousMarginalLikelihood", "likelihood",
           "continuous_likelihood", "noise_likelihood", "LIKELIHOODS"]

LIKELIHOODS = {"table": likelihood, "command_poly": continuous_likelihood}     # by the model's ``action.kind``


def noise_likelihood(log: Log, model: Model, poses: np.ndarray) -> NoiseLikelihood:
    """p(O | noise levels) of ``model`` on ``log``, linearised at the MAP from ``poses`` (T+1, 3), in the form of
    its kind of action model: an action table's on a pose every step, a command map's on its calibration's knots."""
    return LIKELIHOODS[model.action.kind](log, model, poses)
