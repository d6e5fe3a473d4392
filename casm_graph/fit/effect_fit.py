"""Fit a model with effects on the full graph, warm-started from a fitted model and its trajectory.

Rounds of least squares over poses, table, polynomial and the effects' parameters, each followed
by the noise step (sigmas and noise-only effect parameters), as the base method does. The least squares
maximise the joint density, the fit is judged by the Laplace log-likelihood: a fit whose rounds leave it more
than ``LIKELIHOOD_DROP`` below where it started (or below an earlier round) returns that better state, so that
a model with an effect added never reads worse than the model it started from.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from casm_graph.fit.result import LIKELIHOOD_DROP
from casm_graph.fit.solve import least_squares
from casm_graph.graph import table as G
from casm_graph.graph.augmented import at_prior_widths, begin, estimate_noise, instantiate, theta_from_model
from casm_graph.graph.problem import Problem, State
from casm_graph.io.log import Log
from casm_graph.models.effects import Effect
from casm_graph.models.model import Model

ROUNDS = 3
ITERATIONS = 10


@dataclass
class EffectFit:
    model: Model                 # with ``effects`` filled in
    poses: np.ndarray
    theta: np.ndarray
    effects: list
    problem: Problem
    state: State
    log_likelihood: float
    iterations: int
    cost: list
    kept_round: int | None = None      # the earlier state returned (0: the start) when the last round fell below it
    last_log_likelihood: float | None = None   # ... and where that last round ended
    tried: list = field(default_factory=list)  # :func:`likeliest`: each prior-width choice's widths, log-likelihood
                                               # and iterations (empty: a single choice)


def describe(effects: list[Effect], problem: Problem, theta: np.ndarray) -> dict:
    return {e.name: e.describe(theta[s]) for e, s in zip(effects, problem.slices)}


def fit(log: Log, model: Model, poses: np.ndarray, effects, theta: np.ndarray | None = None,
        rounds: int = ROUNDS, iterations: int = ITERATIONS, obs_mask: np.ndarray | None = None,
        seed: int = 0, fit_parameters: bool = True, on_iteration=None, rel_tol: float = 1e-6,
        fit_noise: bool = True) -> EffectFit:
    """Least squares with ``effects`` from ``model`` and ``poses`` (T+1, 3); noise re-estimated each round.

    ``fit_parameters=False`` keeps table, polynomial, effects and noise where they are and only
    moves the poses (how a given model is assessed on a log); ``fit_noise=False`` keeps only the
    noise levels (and noise-only effect parameters) where they are.
    """
    effects = instantiate(effects, log)
    begin(effects, model, poses)
    th = theta_from_model(effects, model) if theta is None else np.asarray(theta, float)
    cost, its = [], 0
    anchor = G.heading_anchor(log, poses)
    problem = Problem(log, model, effects, theta=th, obs_mask=obs_mask, huber=False, anchor=anchor)
    st = problem.state(poses, model, th)
    problem.refresh_noise_state(st)
    best = (problem.log_likelihood(st), model, st, 0) if fit_parameters else None
    mixture = any(e.outlier_fraction(th[sl]) > 0 for e, sl in zip(effects, problem.slices))
    # with fixed parameters one round, or two for a mixture, whose inlier weights follow the poses
    for r in range(rounds if fit_parameters else 1 + mixture):
        st, h = least_squares(problem, st, max_iterations=iterations, on_iteration=on_iteration,
                              freeze_parameters=not fit_parameters, rel_tol=rel_tol)
        its += h.iterations
        cost.extend(h.cost)
        model = problem.with_state(model, st)
        if fit_parameters and fit_noise:
            model, theta_new = estimate_noise(problem, st, model, seed=seed + r)
            st = State(st.poses, st.velocities, st.poly, theta_new)
        problem = judged(log, model, effects, st.theta, obs_mask, anchor, st)
        if best is not None and r < rounds - 1:
            ll = problem.log_likelihood(st)
            if ll > best[0]:
                best = (ll, model, st, r + 1)
    ll = problem.log_likelihood(st)
    kept = last = None
    if best is not None and ll < best[0] - LIKELIHOOD_DROP:
        last = ll
        ll, model, st, kept = best
        problem = judged(log, model, effects, st.theta, obs_mask, anchor, st)
    model = model.with_(effects=describe(effects, problem, st.theta))
    return EffectFit(model, st.poses, st.theta, effects, problem, st, ll, its, cost, kept, last)


def likeliest(log: Log, model: Model, poses: np.ndarray, effects, *args, **kwargs) -> EffectFit:
    """:func:`fit` under each choice of the effects' prior widths (:func:`~casm_graph.graph.augmented.at_prior_widths`),
    the fit of highest log-likelihood kept, its ``tried`` listing every choice. A loose prior lets a shape's weakly
    pinned directions wander into a worse basin, a tight one holds a large effect back: the data choose, in every fit
    that frees such an effect (a calibration, a diagnosis's candidate and its held-out folds)."""
    choices = at_prior_widths(effects, log)
    if len(choices) == 1:
        return fit(log, model, poses, choices[0], *args, **kwargs)
    fits, tried = [], []
    for chosen in choices:                  # a width ``model`` records for an effect would override the choice
        widths = {e.name: e.prior_width for e in chosen if len(e.prior_widths) > 1}
        at = model.with_(effects={n: {**entry, "prior_width": widths[n]} if n in widths else entry
                                  for n, entry in model.effects.items()})
        f = fit(log, at, poses, chosen, *args, **kwargs)
        fits.append(f)
        tried.append({"prior_width": widths, "log_likelihood": f.log_likelihood, "iterations": f.iterations})
    best = max(fits, key=lambda f: f.log_likelihood if np.isfinite(f.log_likelihood) else -np.inf)
    best.tried = tried
    return best


def judged(log, model, effects, theta, obs_mask, anchor, st: State) -> Problem:
    """The effect graph of ``model`` with its reading scales and inlier weights taken at ``st``: what a round's
    least squares run on and the log-likelihood is read from."""
    problem = Problem(log, model, effects, theta=theta, obs_mask=obs_mask, huber=False, anchor=anchor)
    problem.refresh_noise_state(st)
    return problem
