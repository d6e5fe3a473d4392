"""The factor-graph method: a global start, a coarse graph to settle the trajectory, then the full graph.

1. :func:`casm_graph.fit.initialise.initialise` finds trajectory, table and sensor curve with no
   least squares (no local minima to fall into).
2. A coarse graph (a pose every ``stride`` steps) is optimised in rounds; after each round every
   noise level is re-estimated from its residuals with the degrees-of-freedom correction of
   :mod:`casm_graph.graph.noise`, so the motion noise starts at the paper's loose value and tightens as
   the fit earns it. A whole turn the start wound into a few knots (across a gap in the sightings, say) is
   unwound after each round's least squares and kept when the graph agrees (:func:`casm_graph.fit.turns.unspun`).
3. Sightings the coarse fit cannot explain by any Gaussian noise are pruned
   (:mod:`casm_graph.fit.outliers`, as the paper prunes in its first EM iteration); the coarse
   trajectory is filled in step by step and the full graph (a pose every step, as in the paper)
   is optimised, its noise levels re-estimated once more, and the Gaussian marginals (a selected
   inversion of the pose chain, :func:`casm_graph.fit.solve.chain_marginals`) give the posterior std
   of every pose, velocity and coefficient.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from functools import partial

import numpy as np

from casm_graph.fit.initialise import initialise
from casm_graph.fit.methods.base import Fit, Progress, register
from casm_graph.fit.outliers import set_aside
from casm_graph.fit.residuals import distances, observation
from casm_graph.fit.sensor_degree import SensorCurveOptions, better_curve, choose_curve, suspect
from casm_graph.fit.solve import RIDGE_WARNING, chain_marginals, least_squares, world_std
from casm_graph.fit import turns
from casm_graph.graph import table as G
from casm_graph.graph.augmented import estimate_noise
from casm_graph.graph.problem import Problem
from casm_graph.io.log import Log
from casm_graph.models.effects.false_detections import FalseDetections, mixture_terms, reading_span, share
from casm_graph.models.model import Model

HEADING_AGREEMENT = 0.9      # ranges only: chained headings agreeing less than this make the start doubtful
HEADING_WARNING = ("ranges alone place this robot's headings poorly ({}): the model may be wrong; bearings, "
                   "longer runs of each action or more precise ranges fix the headings better")


@dataclass(frozen=True)
class GraphOptions:
    """How the factor-graph method searches (stages 2-3 of the module docstring); recorded in model.json
    ``fit.options.graph``."""

    coarse_stride: int = 10               # command steps per pose of the coarse graph
    coarse_rounds: int = 6                # coarse rounds, each LM then the noise step
    coarse_iterations: int = 5            # LM iterations per coarse round
    coarse_relax: float = 1.0             # over-relaxation of the coarse noise step (in log sigma)
    realias_after: tuple[int, ...] = (2, 4)   # coarse rounds after which every action's turn-rate alias is re-picked
    full_iterations: int = 15             # LM iterations per full round
    full_rounds: int = 2                  # full rounds (the noise step between them)
    sensor_curve: SensorCurveOptions = field(default_factory=SensorCurveOptions)   # when the data move the curve

    def to_json(self) -> dict:
        return {**asdict(self), "realias_after": list(self.realias_after)}


def fill_in(log: Log, model: Model, lay: G.Layout, knot_poses: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses: each coarse segment dead-reckoned step by step, its closure error spread linearly."""
    return G.fill_between(lay.knots, knot_poses, model.velocity_of(log.action) * log.dt[:, None])


def log_likelihood(cost: float, lay: G.Layout, log: Log, model: Model) -> float:
    """Gaussian log-likelihood of the data terms at the optimum (GTSAM cost is half the chi-square)."""
    n_r = int(np.sum(~np.isnan(log.obs_reading)))
    n_b = int(np.sum(~np.isnan(log.obs_bearing)))
    sig = np.asarray(model.motion_noise, float)
    log_det = (np.sum(np.log(sig)) * (lay.n_poses - 1) + 1.5 * np.sum(np.log(lay.seg_steps))
               + n_r * np.log(model.reading_sigma) + n_b * np.log(model.bearing_sigma))
    n = 3 * (lay.n_poses - 1) + n_r + n_b
    return float(-cost - log_det - 0.5 * n * np.log(2 * np.pi))


def mixture_weights(log: Log, poses_at_obs: np.ndarray, model: Model, fraction: float) -> tuple[np.ndarray, float]:
    """Every sighting's inlier weight under the false-detection mixture at ``fraction`` (the effect's own
    formula), and the fraction's EM update: how ``--effect false_detections`` acts from the first round."""
    r, b = observation(poses_at_obs, log, model)
    w = mixture_terms(r, b, model.reading_sigma, model.bearing_sigma, fraction, reading_span(log.obs_reading))["weight"]
    return w, share(w)


def _optimise(log, lay, model, poses, iterations, cost, stages, label, progress, weight=None):
    """``iterations`` LM steps on ``lay``'s graph from ``poses``, a spin unwound (:func:`casm_graph.fit.turns.unspun`).
    Returns the problem, its state, the model there, the last history and the LM iterations spent."""
    problem = Problem(log, model, lay=lay, weight=weight, anchor=G.heading_anchor(log, poses))

    def tick(c):
        cost.append(c)
        stages.append(label)
        progress.step(0, cost=c)

    st, h = least_squares(problem, problem.state(poses, model), max_iterations=iterations, on_iteration=tick)
    st, spun, more = turns.unspun(problem, st, h, partial(least_squares, problem, max_iterations=iterations,
                                                         on_iteration=tick), span=lay.seg_steps * lay.seg_dt)
    return problem, st, problem.with_state(model, st), spun, h.iterations + more


@dataclass
class Coarse:
    """The global start settled on a coarse graph: model, poses at every step, and how it got there."""

    model: Model
    poses: np.ndarray
    cost: list
    stages: list
    iterations: int
    realiased: list
    init: object
    fraction: float = 0.0          # false-detection share (the mixture's, when fitted)


def realias_if_better(log: Log, lay: G.Layout, model: Model, poses: np.ndarray, iterations: int,
                      weight: np.ndarray | None) -> tuple[Model, np.ndarray, list[int]]:
    """:func:`casm_graph.fit.turns.realias`, kept only when the graph agrees: the trajectory with the picked aliases
    and the one without, each settled by ``iterations`` LM steps under the same noise levels, the lower cost wins
    (the aliases are scored on each run's own dead-reckoned sightings, which a short log can fool: a one-minute
    Aibo log took a wrong alias and ended 0.68 m off)."""
    new_model, new_poses, changed = turns.realias(log, lay, model, poses)
    if not changed:
        return model, poses, []

    def settle(m, p):
        _, st, settled, h, _ = _optimise(log, lay, m, p, iterations, [], [], "realias", Progress(), weight)
        return h.cost[-1], settled, st.poses

    kept, picked = settle(model, poses), settle(new_model, new_poses)
    return (picked[1], picked[2], changed) if picked[0] < kept[0] else (kept[1], kept[2], [])


def coarse_start(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
                 mixture: bool = False, options: GraphOptions | None = None) -> Coarse:
    """Stages 1-3 of the module docstring: global initialisation, then the coarse graph in rounds
    (``mixture``: sightings weighted by the false-detection mixture, its share re-estimated each round)."""
    o = options or GraphOptions()
    progress = progress or Progress()
    cost, stages, iterations = [], [], 0
    realiased: list[int] = []
    progress.stage("initialise", None)
    init = initialise(log, start)
    bearings = "bearing" in log.channels
    if not bearings and not init.heading_agreement >= HEADING_AGREEMENT:
        why = (f"consecutive moves agree to {init.heading_agreement:.2f}, under {HEADING_AGREEMENT}"
               if np.isfinite(init.heading_agreement) else "too few repeated moves to check them")
        warnings.warn(HEADING_WARNING.format(why), RuntimeWarning, stacklevel=2)
    model = init.model.with_(motion_noise=np.asarray(start.motion_noise, float),
                             bearing_sigma=float(start.bearing_sigma))
    lay = G.layout(log, model, stride=o.coarse_stride)
    poses = init.poses[lay.knots]
    fraction, weight = (FalseDetections.start[0] if mixture else 0.0), None
    progress.stage("coarse graph", o.coarse_rounds)
    for r in range(o.coarse_rounds):
        if mixture:
            weight, fraction = mixture_weights(log, poses[lay.obs_knot], model, fraction)
        problem, st, model, h, its = _optimise(log, lay, model, poses, o.coarse_iterations, cost, stages,
                                               "coarse", progress, weight)
        iterations += its
        poses = st.poses
        model = estimate_noise(problem, st, model, seed=seed + r, relax=o.coarse_relax)[0]
        if r in o.realias_after and bearings:    # ranges only: the start's links already chose among the aliases
            model, poses, changed = realias_if_better(log, lay, model, poses, o.coarse_iterations, weight)
            realiased.extend(changed)
        progress.step(1)
    return Coarse(model, fill_in(log, model, lay, poses), cost, stages, iterations, realiased, init, fraction)


@register("graph")
def fit(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
        marginals: bool = True, mixture: bool = False, options: GraphOptions | None = None,
        max_sensor_degree: int = 0, free_basis: bool = False) -> Fit:
    """Calibrate ``log`` from the paper's start ``start`` with the factor graph (``mixture``: with the
    false-detection mixture in every round, as ``--effect false_detections`` asks; ``max_sensor_degree``:
    the sensor polynomial's degree may rise to it when the data demand; ``free_basis``: when the fit in d
    shows a near-range misfit, a fit with the curve in 1/d competes, :mod:`casm_graph.fit.sensor_degree`)."""
    progress = progress or Progress()
    options = options or GraphOptions()
    first = _fit(log, start, seed, progress, marginals, mixture, options, max_sensor_degree)
    if not (free_basis and start.reading_basis == "distance" and suspect(first.model, log, options.sensor_curve)):
        return first
    progress.stage("the sensor curve in 1/d", None)
    other = _fit(log, start.with_(reading_basis="inverse_distance"), seed, progress, marginals, mixture, options,
                 max_sensor_degree)
    return better_curve(log, first, other, sighting_log_likelihood, options.sensor_curve,
                        [FalseDetections()] if mixture else ())


def sighting_log_likelihood(log: Log, fit: Fit) -> float:
    """:func:`log_likelihood` of ``fit`` at its poses and noise levels on every sighting of ``log`` (the pruned
    ones too, through Huber's loss): fits that pruned different sightings scored on the same data."""
    lay = G.layout(log, fit.model, stride=1)
    problem = Problem(log, fit.model, lay=lay)
    return log_likelihood(problem.cost(problem.state(fit.poses, fit.model)), lay, log, fit.model)


def _fit(log: Log, start: Model, seed: int, progress: Progress, marginals: bool, mixture: bool,
         o: GraphOptions, max_sensor_degree: int) -> Fit:
    """One calibration from ``start`` (:func:`fit`'s arguments)."""
    t0 = time.perf_counter()
    co = coarse_start(log, start, seed, progress, mixture, o)
    fraction, weight = co.fraction, None
    model, poses, cost, stages, iterations = co.model, co.poses, co.cost, co.stages, co.iterations
    realiased, init = co.realiased, co.init
    unpruned = log
    log, pruned = set_aside(log, model, poses)

    full = G.layout(log, model, stride=1)
    asked = len(model.reading_poly) - 1
    progress.stage("full graph", o.full_rounds)
    for attempt in range(2):
        for r in range(o.full_rounds):
            if mixture:
                weight, fraction = mixture_weights(log, poses[log.obs_step], model, fraction)
            problem, st, model, h, its = _optimise(log, full, model, poses, o.full_iterations, cost, stages,
                                                   "full", progress, weight)
            iterations += its
            poses = st.poses
            if r < o.full_rounds - 1:
                model = estimate_noise(problem, st, model, seed=seed + 100 + r)[0]
            progress.step(1)
        ok = ~np.isnan(log.obs_reading)         # the readings' distances, kept for distance_range below
        d = distances(poses[log.obs_step], log)[ok]
        better = None if attempt else choose_curve(d, log.obs_reading[ok], model.reading_poly,
                                                   model.reading_sigma, max_sensor_degree, model.reading_basis,
                                                   o.sensor_curve)
        if better is None:
            break
        model = model.with_(reading_poly=better[0], reading_basis=better[1])   # the data demand another curve:
        log, pruned = set_aside(unpruned, model, poses)                        # its outliers, the full graph again
        progress.stage(f"full graph, sensor degree {len(better[0]) - 1}"
                       + (" in 1/d" if better[1] == "inverse_distance" else ""), o.full_rounds)
    converged = h.converged
    final_cost = problem.cost(st)

    pose_std, ridge = np.full_like(poses, np.nan), None
    if marginals:
        progress.stage("marginals", None)
        m, ridge = chain_marginals(problem, st)
        if ridge:
            warnings.warn(RIDGE_WARNING.format(ridge), RuntimeWarning, stacklevel=2)
        cov_xy = m.pose_cov[:, :2, :2]
        pose_std = np.sqrt(np.diagonal(m.pose_cov, axis1=1, axis2=2))
        nv = 3 * full.n_actions
        vstd = np.sqrt(np.diag(m.param_cov)[:nv]).reshape(full.n_actions, 3)
        ccov = m.param_cov[nv:, nv:].copy()
        model = model.with_(velocity_std=vstd, reading_poly_std=np.sqrt(np.diag(ccov)), reading_poly_cov=ccov)
        pose_std = world_std(poses, pose_std, cov_xy)
    ll = log_likelihood(final_cost, full, log, model)
    model = model.with_(distance_range=(float(d.min()), float(d.max())) if len(d) else (0.0, 0.0),
                        fit={"method": "graph", "iterations": iterations,
                             "seconds": round(time.perf_counter() - t0, 3),
                             "log_likelihood": ll, "converged": bool(converged),
                             "outliers_pruned": int(pruned.sum()),
                             "sensor_degree": {"asked": asked, "fitted": len(model.reading_poly) - 1,
                                               "basis": model.reading_basis},
                             **({} if "bearing" in log.channels else {"heading_agreement": (
                                 round(init.heading_agreement, 4) if np.isfinite(init.heading_agreement) else None)})},
                        effects={FalseDetections.name: {"fraction": fraction}} if mixture else {})
    return Fit(model=model, poses=poses, pose_std=pose_std, cost=cost, stages=stages,
               iterations=iterations, converged=converged, log_likelihood=ll,
               notes={"hypothesis": list(init.hypothesis), "start_log_evidence": init.log_evidence,
                      "heading_agreement": init.heading_agreement,
                      "realiased_actions": realiased, "marginals_ridge": ridge,
                      "outliers_pruned": np.flatnonzero(pruned).tolist()})
