"""Calibrating an action table (discrete actions): the paper's zero table, the windowed initialiser, the coarse
graph of :mod:`casm_graph.fit.methods.graph`, any method, and effects refitted on the base fit's full graph."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from casm_graph.fit import effect_fit
from casm_graph.fit.initialise import initialise
from casm_graph.fit.methods.base import METHODS, Fit, Progress
from casm_graph.fit.methods.graph import coarse_start
from casm_graph.fit.methods.kinds.base import ActionKind
from casm_graph.fit.result import LIKELIHOOD_DROP
from casm_graph.fit.solve import world_std
from casm_graph.graph import augmented
from casm_graph.io.log import Log, LogError
from casm_graph.models.effects import of_model
from casm_graph.models.model import paper_start
from casm_graph.models.velocity_table import KIND


def kept(log: Log, fit: Fit) -> np.ndarray:
    """The sightings ``fit`` kept: its pruned outliers stay out of every later graph, as they did there."""
    keep = np.ones(len(log.obs_t), bool)
    keep[np.asarray(fit.notes.get("outliers_pruned", []), int)] = False
    return keep


def on_step_graph(log: Log, fit: Fit) -> Fit:
    """``fit`` with its log-likelihood taken on the graph with a pose every step (its poses settled there, the model
    held), the graph effects are fitted on, so that a model and the same model with an effect added compare as a
    likelihood ratio; the coarse graph's motion rows each span a segment of steps, another quantity (an Aibo log's
    64,346 there against -5,502 here, and -5,492 with a battery fade added)."""
    step = effect_fit.fit(log, fit.model, fit.poses, of_model(fit.model.effects), fit_parameters=False,
                          obs_mask=kept(log, fit))
    ll = float(step.log_likelihood)
    return replace(fit, log_likelihood=ll, model=fit.model.with_(fit={**fit.model.fit, "log_likelihood": ll}),
                   notes={**fit.notes, "coarse_log_likelihood": fit.log_likelihood})


def with_effects(log: Log, fit: Fit, effects, seed: int = 0, progress: Progress | None = None) -> Fit:
    """Refit ``fit`` with ``effects`` added (warm start), under each choice of their priors' widths, keeping the fit
    of highest log-likelihood; std of poses, table and polynomial from the effect graph."""
    t0 = time.perf_counter()
    mask = kept(log, fit)
    if progress is not None:
        progress.stage("effects", effect_fit.ROUNDS * len(augmented.at_prior_widths(effects, log)))
    ef = effect_fit.likeliest(log, fit.model, fit.poses, effects, seed=seed, obs_mask=mask,
                              on_iteration=(lambda c: progress.step(0, cost=c)) if progress is not None else None)
    its = sum(t["iterations"] for t in ef.tried) if ef.tried else ef.iterations
    cov_p, cov_t = augmented.marginals(ef.problem, ef.state)
    na, D = ef.problem.n_action, ef.problem.D
    sd = np.sqrt(np.clip(np.diag(cov_t), 0, None))
    effect_std = {}
    for e, s in zip(ef.effects, ef.problem.slices):
        if not e.noise_only:
            cols = [na + D + int(np.flatnonzero(ef.problem.ls_index == i)[0]) for i in range(s.start, s.stop)]
            effect_std[e.name] = {p: float(sd[c]) for p, c in zip(e.params, cols)}
    compared = {} if ef.kept_round is None else {"kept_round": ef.kept_round,
                                                  "last_log_likelihood": ef.last_log_likelihood}
    if ef.log_likelihood < fit.log_likelihood - LIKELIHOOD_DROP and not any(e.noise_only for e in ef.effects):
        # the base's figure holds its own noise levels: the base refitted as the effects were, to compare with
        compared["refit_log_likelihood"] = effect_fit.fit(log, fit.model, fit.poses, [], seed=seed,
                                                          obs_mask=mask).log_likelihood
    pose_std = world_std(ef.poses, np.sqrt(np.einsum("kii->ki", cov_p)), cov_p[:, :2, :2])
    model = ef.model.with_(velocity_std=sd[:na].reshape(-1, 3), reading_poly_std=sd[na:na + D],
                           reading_poly_cov=cov_t[na:na + D, na:na + D],
                           fit={**fit.model.fit, "iterations": fit.model.fit.get("iterations", 0) + its,
                                "seconds": round(fit.model.fit.get("seconds", 0) + time.perf_counter() - t0, 3),
                                "log_likelihood": ef.log_likelihood, "effects_std": effect_std,
                                **({"prior_widths_tried": ef.tried} if ef.tried else {}),
                                **({} if ef.kept_round is None else {"kept_round": ef.kept_round})})
    return Fit(model=model, poses=ef.poses, pose_std=pose_std, cost=fit.cost + ef.cost,
               stages=fit.stages + ["effects"] * len(ef.cost), iterations=fit.iterations + its,
               converged=fit.converged, log_likelihood=ef.log_likelihood,
               notes={**fit.notes, "base_log_likelihood": fit.log_likelihood, **compared,
                      "hooked_effects": [type(e) for e in ef.effects]})


class TableKind(ActionKind):
    name = KIND

    def start_model(self, log, sensor_degree=3, basis="distance", cross=False, step_heading="start"):
        return paper_start(log, sensor_degree, basis)

    def initialise(self, log, start):
        return initialise(log, start)

    def coarse(self, log, start, seed=0, progress=None, options=None):
        return coarse_start(log, start, seed, progress, options=options)

    def check(self, log, options, classes):
        if options.step_heading == "middle":
            raise LogError(f"--step-heading {options.step_heading}: an action table's velocities are the paper's, "
                           f"per step along its start heading (continuous commands only)")
        for cls in classes:
            why = cls(log).applicable(log)
            if why:
                raise LogError(f"effect {cls.name!r} cannot be fitted on {log.source or 'this log'}: {why}")

    def calibrate(self, log, start, options, classes, progress=None):
        mixture = options.method == "graph" and any(cls.name == "false_detections" for cls in classes)
        extra = {"options": options.graph} if options.method in ("graph", "graph-em") else {}
        if options.method == "graph":
            extra["max_sensor_degree"] = options.max_sensor_degree
            extra["free_basis"] = options.sensor_basis == "auto" and options.max_sensor_degree > options.sensor_degree
        fit = METHODS[options.method](log, start, seed=options.seed, progress=progress,
                                      **({"mixture": True} if mixture else {}), **extra)
        if options.method == "graph":
            fit = on_step_graph(log, fit)
        if classes:
            fit = with_effects(log, fit, classes, seed=options.seed, progress=progress)
        return fit
