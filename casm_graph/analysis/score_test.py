"""Score (Lagrange multiplier) test of a candidate effect at the base fit: what it could gain, before fitting it.

At the base fit the gradient in the base's variables is (nearly) zero. With the candidate added at its start
value, one Gauss-Newton step with poses, table, polynomial and every least-squares parameter free predicts how far
the whitened cost falls: half the score statistic, the effect's parameters' gradient weighed by their information
with everything else profiled out. One linearisation and one solve on the pose chain, where fitting the candidate
costs some twenty of them and the noise rounds; a diagnosis fits only the candidates whose predicted gain is a
material share of their BIC penalty.
"""
from __future__ import annotations

import numpy as np

from casm_graph.graph import table as G
from casm_graph.graph.problem import Problem, State

RIDGES = (0.0, 1e-9, 1e-6)        # damping tried when the undamped system is singular to machine precision


def predicted_floor(problem: Problem, st: State) -> float:
    """The cost one undamped Gauss-Newton step from ``st`` predicts: ``problem.cost(st)`` less the quadratic
    model's decrease ``-g^T delta / 2`` (``delta = -H^-1 g``)."""
    cost = problem.cost(st)
    neq = problem.normal_equations(st)
    _, _, _, gp, _, gt = neq
    for lam in RIDGES:
        try:
            dp, dt = problem.solve_damped(neq, lam)
        except np.linalg.LinAlgError:
            continue
        decrease = -0.5 * (float(np.sum(gp * dp)) + float(np.dot(gt, dt)))
        return cost - max(decrease, 0.0) if np.isfinite(decrease) else cost
    return cost


def predicted_gain(log, base, effect, floor: float | None = None) -> float | None:
    """The log-likelihood ``effect`` (an instance) would add to ``base`` (an :class:`~casm_graph.fit.effect_fit.EffectFit`)
    at the base's noise levels, by the score test; None for an effect the noise step sets (no least-squares
    parameters to test). ``floor``: :func:`predicted_floor` of the base, when already computed."""
    if effect.noise_only:
        return None
    if floor is None:
        floor = predicted_floor(base.problem, base.state)
    effects = list(base.effects) + [effect]
    theta = np.concatenate([np.asarray(base.theta, float), np.asarray(effect.start, float)])
    problem = Problem(log, base.model, effects, theta=theta, huber=False, anchor=G.heading_anchor(log, base.poses))
    st = problem.state(base.poses, base.model, theta)
    problem.refresh_noise_state(st)
    return float(floor - predicted_floor(problem, st))
