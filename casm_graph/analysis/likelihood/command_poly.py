"""log p(O | lambda) of a continuous-command log (:class:`ContinuousMarginalLikelihood`): the same concept on the
graph of :mod:`casm_graph.fit.continuous`, pose knots, one command-map vector and the sensor polynomial integrated out.

Each noise channel's rows share one scale there, so H = sum_c H_c / lambda_c^2 + prior with the
H_c assembled once; every call adds them up on one sparsity pattern and factors H with a sparse
LU in the chain order (knots in time, then the parameters: no fill but the parameters' border).
Only the channels the log measures carry a noise level.
"""
from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from casm_graph.analysis.likelihood.base import (LOG2PI, MOTION_NAMES, NoiseLikelihood, NoiseParameter,
                                                 length_factors)
from casm_graph.fit import continuous as CT
from casm_graph.fit.solve import least_squares
from casm_graph.graph.problem import Problem, State
from casm_graph.io.log import Log
from casm_graph.models.model import Model


CHANNEL_PARAMS = (("reading", "reading", 0, "reading_sigma"), ("bearing", "bearing", 0, "bearing_sigma"),
                  ("forward", "motion", 0, MOTION_NAMES[0]), ("lateral", "motion", 1, MOTION_NAMES[1]),
                  ("turn", "motion", 2, MOTION_NAMES[2]))   # (row group, kind, motion axis, name), the table's order


def _on_pattern(parts: list, n: int) -> tuple[np.ndarray, np.ndarray, list]:
    """(indices, indptr) of the CSC pattern of the sum of the sparse (n, n) ``parts``, and each part's values on it."""
    total = sum(abs(p) for p in parts).tocsc()
    total.eliminate_zeros()
    total.sort_indices()
    keys = total.indices.astype(np.int64) + n * np.repeat(np.arange(n, dtype=np.int64), np.diff(total.indptr))
    values = []
    for p in parts:
        c = p.tocsc()
        c.sum_duplicates()
        c.eliminate_zeros()
        c.sort_indices()
        k = c.indices.astype(np.int64) + n * np.repeat(np.arange(n, dtype=np.int64), np.diff(c.indptr))
        v = np.zeros(total.nnz)
        v[np.searchsorted(keys, k)] = c.data
        values.append(v)
    return total.indices, total.indptr, values


def unit_rows(problem: Problem, st: State, model: Model):
    """The continuous graph's Jacobian A, residual e and row groups at unit noise levels, no Huber weights, and the
    length factors' log-det constant.

    Motion rows are whitened by each segment's length factor only (:func:`length_factors`), sighting rows are
    raw: dividing them by lambda gives the rows at noise levels lambda.
    """
    unit = copy.copy(problem)
    unit.motion_sigma, const = length_factors(problem, model)
    unit.reading_sigma = unit.bearing_sigma = 1.0
    unit.k = np.inf
    return (*unit.jacobian(st), const)


class ContinuousMarginalLikelihood(NoiseLikelihood):
    """log p(O | lambda) of a continuous-command log, knots, command map and polynomial integrated out.

    Linearised once at the MAP ``st`` of ``problem`` (the model's noise levels, its outliers set
    aside); every call weights each channel's rows by 1 / lambda_c^2 and factors
    H = A' W A + priors with SuperLU in the chain order (knots in time, then the command map and
    the polynomial; no pivoting, H being positive definite), log det H from U's diagonal:

        log p(O | lambda) = sum_rows log N(e0_row; 0, sigma_row^2) + 1/2 g' H^-1 g - 1/2 log det H + const.

    The noise levels are the channels the log measures, each sampled as in the table graph:
    reading and bearing sigma, forward, lateral and turn motion noise per median command step.
    The profiled effects' parameters (``actuator_lag``'s time constant, ``lens_distortion``'s k) stay as
    calibrated; hooked effects' parameters are integrated out with the command map (the parameter vector holds
    both).
    """

    @property
    def integrated_out(self) -> tuple[str, ...]:
        hooked = ("effect parameters",) if len(self.problem.ls_index) else ()
        return ("poses (knots)", "command map", *hooked, "sensor polynomial")

    def set_aside(self) -> int:
        return self._set_aside

    def __init__(self, problem: Problem, st: State, model: Model):
        self.problem, self.state, self.model = problem, st, model
        self._set_aside = problem.set_aside(model)
        A, e, groups, lengths = unit_rows(problem, st, model)
        n = A.shape[1]
        self.n = n
        self.par = np.arange(3 * problem.lay.n_poses, n)
        motion = np.asarray(model.motion_noise, float)
        self.params, rows, parts = [], [], []
        for channel, kind, index, name in CHANNEL_PARAMS:
            r = groups[channel]
            if not len(r) or (kind != "motion" and not model.has(kind)):
                continue                     # a channel the log does not measure has no noise level
            value = motion[index] if kind == "motion" else getattr(model, f"{kind}_sigma")
            self.params.append(NoiseParameter(name, kind, index, float(value)))
            rows.append(r)
        self.names = [p.name for p in self.params]
        self.x_map = np.array([p.value for p in self.params])
        prior = np.setdiff1d(np.arange(A.shape[0]), np.concatenate(rows) if rows else [])
        for r in rows + [prior]:
            Ar = A[r]
            parts.append((Ar.T @ Ar).tocsc())
        self.indices, self.indptr, values = _on_pattern(parts, n)
        self.H_parts, self.H_prior = np.array(values[:-1]), values[-1]
        self.g_parts = np.array([A[r].T @ e[r] for r in rows])
        self.g_prior = A[prior].T @ e[prior]
        self.ss = np.array([float(e[r] @ e[r]) for r in rows])
        self.counts = np.array([len(r) for r in rows], float)
        self.ss_prior = float(e[prior] @ e[prior])
        self.const = lengths - 0.5 * float(np.sum(self.counts)) * LOG2PI

    def _split(self, x):
        """(reading sigma, bearing sigma, motion noise (3,), effect theta) from a vector of noise levels, the model's
        elsewhere (the noise effects' parameters are the calibration's: not sampled here)."""
        mot = np.array(self.model.motion_noise, float)
        sr, sb = float(self.model.reading_sigma), float(self.model.bearing_sigma)
        for p, v in zip(self.params, np.asarray(x, float)):
            if p.kind == "reading":
                sr = float(v)
            elif p.kind == "bearing":
                sb = float(v)
            else:
                mot[p.index] = v
        return sr, sb, mot, self.state.theta.copy()

    def system(self, x):
        """(data log density at the MAP residuals, H as CSC, g) at noise levels ``x``."""
        w = 1.0 / np.asarray(x, float) ** 2
        ldata = float(self.const - 0.5 * np.sum(self.ss * w) - np.sum(self.counts * np.log(x))
                      - 0.5 * self.ss_prior)
        H = sp.csc_matrix((w @ self.H_parts + self.H_prior, self.indices, self.indptr), shape=(self.n, self.n))
        return ldata, H, w @ self.g_parts + self.g_prior

    def factor(self, x):
        """(data log density, SuperLU of H in the chain order, g); the LU is None where H is not positive definite."""
        ldata, H, g = self.system(x)
        try:
            lu = splu(H, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError:
            return ldata, None, g
        return ldata, lu, g

    def terms(self, x) -> tuple[float, float, float]:
        """(data log density at the MAP residuals, log det H, g' H^-1 g)."""
        ldata, lu, g = self.factor(np.asarray(x, float))
        if lu is None:
            return ldata, np.nan, np.nan
        d = lu.U.diagonal()
        if not np.all(d > 0):
            return ldata, np.nan, np.nan
        return ldata, float(np.sum(np.log(d))), float(g @ lu.solve(g))

    def __call__(self, x) -> float:
        """log p(O | x) up to a constant: the Laplace value with knots, command map and polynomial integrated."""
        x = np.asarray(x, float)
        if not self.in_support(x):
            return -np.inf
        ldata, logdet, gHg = self.terms(x)
        value = ldata + 0.5 * gHg - 0.5 * logdet
        return float(value) if np.isfinite(value) else -np.inf

    def parameter_moments(self, x) -> tuple[np.ndarray, np.ndarray]:
        """(Gauss-Newton shift, Laplace covariance) of the parameter vector (command map, polynomial, effects) at
        ``x``."""
        _, lu, g = self.factor(np.asarray(x, float))
        if lu is None:
            raise np.linalg.LinAlgError("the information matrix is singular at these noise levels")
        E = np.zeros((self.n, len(self.par)))
        E[self.par, np.arange(len(self.par))] = 1.0
        C = lu.solve(E)[self.par]
        return -lu.solve(g)[self.par], 0.5 * (C + C.T)


def continuous_likelihood(log: Log, model: Model, poses: np.ndarray, iterations: int = 10,
                          own=()) -> ContinuousMarginalLikelihood:
    """:class:`ContinuousMarginalLikelihood` of a command-map ``model`` on ``log``, linearised at the MAP from
    ``poses`` (T+1, 3) on the calibration's fine knots, sightings beyond the gate set aside as the fit does;
    the model's hooked effects (``own``: user classes among them) act, their parameters integrated out with
    the command map."""
    lay = CT.layout(log, CT.options_of(model).full_knot_dt)      # the calibration's fine knots
    kp = np.asarray(poses, float)[lay.knots]
    effects = CT.hooked_effects(log, model, own)
    r_use, b_use = CT.gate(log, np.asarray(poses, float)[log.obs_step], model, effects=effects)
    use = (r_use & model.has("reading"), b_use & model.has("bearing"))
    problem = Problem(log, model, effects, lay=lay, gate=use, poses=kp)
    st, _ = least_squares(problem, problem.state(kp, model), max_iterations=iterations)
    return ContinuousMarginalLikelihood(problem, st, model)
