"""An action table's candidates: each effect added to the refitted model and fitted as the calibration fits
(warm start), scored by delta BIC against the same procedure without it and, for those that lower it, by the
held-out log-likelihood on time-blocked folds (:func:`heldout_log_likelihood`). The score test screens out the
candidates that cannot gain enough to be worth fitting; the fits run on worker processes or a Dask cluster
(:mod:`casm_graph.analysis.candidates.pool`)."""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable

import numpy as np

from casm_graph.analysis.candidates.base import Bench
from casm_graph.analysis.candidates.pool import parallel
from casm_graph.analysis.diagnosis import (DECIDED, DEFAULTS, SCREENED, Candidate, DiagnoseOptions, best_of_family,
                                           built_for, chosen_candidates, folds, family_members, is_supported,
                                           leading,
                                           predicted_sightings, strong_structures)
from casm_graph.analysis.score_test import predicted_floor, predicted_gain
from casm_graph.fit import effect_fit
from casm_graph.graph.augmented import begin, instantiate
from casm_graph.io.log import Log
from casm_graph.models.effects import REGISTRY, get, of_model, spec, unphysical
from casm_graph.models.effects.base import held
from casm_graph.models.model import Model


def heldout_log_likelihood(log: Log, model: Model, poses: np.ndarray, effects: list,
                           detail: list | None = None, options: DiagnoseOptions = DEFAULTS) -> float:
    """Sum over folds of log p(hidden block | rest): what the effects and noise levels learned without
    a block say about it (:func:`heldout_fold` per fold).

    ``detail`` (a list) receives per fold the log-likelihood with the block and without it;
    ``options``: the folds and the bounds of each fold's least squares.
    """
    total = 0.0
    for k in range(options.folds):
        with_block, without = heldout_fold(log, model, poses, effects, k, options)
        if detail is not None:
            detail.append({"with_block": with_block, "without_block": without})
        total += with_block - without
    return total


def heldout_fold(log: Log, model: Model, poses: np.ndarray, effects: list, k: int,
                 options: DiagnoseOptions = DEFAULTS) -> tuple[float, float]:
    """Fold ``k``'s log-likelihoods of the whole log with the block and of the rest without it; their difference
    is log p(block | rest).

    The model is fitted on the rest (under each choice of the effects' prior widths, the likelier kept: without a
    block a loose prior's fit can wander into a worse basin); then, with the effects' parameters and the noise
    levels held at those values, table, polynomial and poses are fitted once with the block and once without. The
    table and polynomial are the nuisance here: on a six-minute log many actions run only inside one block, and a
    table learned without it predicts that block so badly (hundreds of nats either way) that the comparison of two
    models drowned in it. The fit with the block starts from the model's own full-log poses: the training poses
    drifted over a block without sightings and could stop in another basin (640 nats lower on one of 36 folds of six
    Aibo effect logs, never more than 0.2 higher: benchmarks/heldout_stability.py --folds); the fit without it is
    the training problem with effects and noise held, so the training poses are already its optimum. ``effects``:
    classes or catalog names.
    """
    effects = [_resolve(e) for e in effects]
    fixed = [held(e) for e in effects]
    its, tol = options.fold_iterations, options.fold_tol
    mask = folds(log, options.folds)[k]
    tr = effect_fit.likeliest(log, model, poses, effects, obs_mask=mask, rounds=1, iterations=its, rel_tol=tol)
    with_block, without = (
        effect_fit.fit(log, tr.model, start, fixed, theta=tr.theta, rounds=1, iterations=its,
                       obs_mask=m, fit_noise=False, rel_tol=tol).log_likelihood
        for m, start in ((None, poses), (mask, tr.poses)))
    return with_block, without


def n_data(log: Log) -> int:
    return int(np.sum(np.isfinite(log.obs_reading)) + np.sum(np.isfinite(log.obs_bearing)))


def _resolve(extra):
    """A catalog name (how effects travel to worker processes) back to its class."""
    return get(extra) if isinstance(extra, str) else extra


def fit_candidate(log: Log, refit: "effect_fit.EffectFit", base: "effect_fit.EffectFit", extra,
                  options: DiagnoseOptions = DEFAULTS, floor: float | None = None, start: tuple | None = None):
    """Fit the refitted model plus ``extra``; delta BIC against ``base`` (the same procedure without it). ``start``:
    (model, poses) to go on from instead (a leader's own fit, for more rounds).

    Returns the candidate (held-out score still to come) and the fitted model and poses. With ``floor`` (the
    base's :func:`~casm_graph.analysis.score_test.predicted_floor`) a candidate whose score-test gain is below
    ``options.screen_share`` of its BIC penalty is not fitted: it returns with the predicted delta BIC,
    ``screened`` set, and no model.
    """
    return scored(fit_member(log, refit, base, extra, options, floor, start), base.log_likelihood)


def fit_member(log: Log, refit: "effect_fit.EffectFit", screen: "effect_fit.EffectFit", extra,
               options: DiagnoseOptions = DEFAULTS, floor: float | None = None, start: tuple | None = None):
    """:func:`fit_candidate` without the base: the score test at ``screen`` (a fit without ``extra``, ``floor`` its
    predicted floor) and, unless screened out, the fit. Returns (candidate, model, poses, (log-likelihood, BIC
    penalty)); :func:`scored` sets the fitted candidate's delta BIC once the base is known, so that the base can be
    fitted beside the candidates."""
    t0 = time.perf_counter()
    eff = instantiate([_resolve(extra)], log)[0]
    begin([eff], refit.model, refit.poses)
    order = eff.order if eff.orders else None
    penalty = eff.free_parameters() * np.log(n_data(log))
    gain = predicted_gain(log, screen, eff, floor) if floor is not None and options.screen_share > 0 else None
    if gain is not None and 2.0 * gain < options.screen_share * penalty:
        return (Candidate(eff.name, eff.channel, float(penalty - 2.0 * gain), float("nan"), eff.physics, gain,
                          {}, time.perf_counter() - t0, heldout_skipped=SCREENED, order=order, screened=True),
                None, None, None)
    model, poses = start if start is not None else (refit.model, refit.poses)
    f = effect_fit.likeliest(log, model, poses, refit.effects + [eff], rounds=options.candidate_rounds,
                             iterations=options.candidate_iterations)
    entry = f.model.effects.get(eff.name, {})
    c = Candidate(eff.name, eff.channel, float("nan"), float("nan"), eff.physics, float("nan"),
                  entry, time.perf_counter() - t0, order=order, prediction=predicted_sightings(f.problem, f.state),
                  implausible=unphysical(type(eff), entry, log) or "")
    return c, f.model, f.poses, (f.log_likelihood, penalty)


def scored(member: tuple, base_log_likelihood: float) -> tuple:
    """(candidate, model, poses) of a :func:`fit_member`, a fitted one's delta log-likelihood and delta BIC against
    the base's log-likelihood."""
    c, model, poses, fitted = member
    if fitted is not None:
        ll, penalty = fitted
        dll = ll - base_log_likelihood
        c.delta_log_likelihood, c.delta_bic = float(dll), float(-2.0 * dll + penalty)
    return c, model, poses


def heldout_rounds(log: Log, base, fitted: list, members: list, matches: Callable, workers: int = 2,
                   progress=None, client=None, options: DiagnoseOptions = DEFAULTS) -> None:
    """Held-out scores (``heldout_nll_drop``) for the fitted candidates that improve BIC, lowest delta BIC first,
    ``workers`` models a round (the base model with the first; each fold a task): once one is supported
    (:func:`is_supported`), only those within the look-alike margin of it can still change the verdict or its
    look-alike group, and the rest keep ``heldout_skipped`` = :data:`DECIDED`. The folds are most of a diagnosis's
    cost.

    ``fitted``: (candidate, model, poses) per member of ``members`` (their classes)."""
    o = options
    queue = sorted((i for i, (c, _, _) in enumerate(fitted) if c.delta_bic < o.heldout_gate and not c.screened),
                   key=lambda i: fitted[i][0].delta_bic)
    if not queue:
        return
    if progress is not None:
        progress.stage("held-out", (len(queue) + 1) * o.folds, unit="folds")
    present = [spec(type(e)) for e in base.effects]
    margin = max(o.bic_tie, o.lookalike_bic)
    base_score = None
    while queue:
        take = queue[:max(workers - (base_score is None), 1)]
        queue = queue[len(take):]
        runs = ([(base.model, base.poses, present)] if base_score is None else []) + [
            (fitted[i][1], fitted[i][2], present + [spec(members[i])]) for i in take]
        pairs = parallel([(heldout_fold, (log, m, p, e, k, o)) for m, p, e in runs for k in range(o.folds)],
                          workers, progress, client)           # every fold of every model a task: none waits
        held = [sum(w - wo for w, wo in pairs[j * o.folds:(j + 1) * o.folds]) for j in range(len(runs))]
        if base_score is None:
            base_score, held = held[0], held[1:]
        for i, h in zip(take, held):
            fitted[i][0].heldout_nll_drop = float(h - base_score)
        lead = next((c for c, _, _ in sorted(fitted, key=lambda f: f[0].delta_bic)
                     if np.isfinite(c.heldout_nll_drop) and is_supported(c, matches, o)), None)
        if lead is not None:
            left = [i for i in queue if fitted[i][0].delta_bic < lead.delta_bic + margin]
            for i in set(queue) - set(left):
                fitted[i][0].heldout_skipped = DECIDED
            if progress is not None and len(left) < len(queue):
                progress.step((len(queue) - len(left)) * o.folds)
            queue = left




class TableBench(Bench):
    """The candidates of an action-table log, refitted with the model and scored in-sample and held out."""

    kind = "table"

    def __init__(self, log: Log, model: Model, poses: np.ndarray, options: DiagnoseOptions = DEFAULTS,
                 extra_effects=(), candidates=None, workers: int = 2, client=None, progress=None, calibrated=None):
        super().__init__(log, model, poses, options)
        o = options
        self.extra_effects, self.workers, self.client, self.progress = extra_effects, workers, client, progress
        pool = {n: REGISTRY[n] for n in sorted(REGISTRY)}
        pool.update({cls.name: cls for cls in extra_effects})
        chosen = chosen_candidates(candidates, extra_effects)
        if chosen is not None:                      # the user narrows the search to these effects
            pool = {n: c for n, c in pool.items() if n in chosen}
        self.pool = list(pool.values())
        if progress is not None:
            progress.stage("refit model", None)
        self.present_names = set(model.effects)
        self.present = present = [spec(c) for c in of_model(model.effects, extra_effects)]   # as they travel
        self.fit = effect_fit.likeliest(log, model, poses, present, rounds=o.candidate_rounds,
                                        iterations=o.candidate_iterations)
        self.base = None             # the fit the candidates are scored against: made beside them (:meth:`score`)
        self.problem, self.state, self.poses = self.fit.problem, self.fit.state, self.fit.poses

    def score(self, structure: list[dict]) -> tuple[list[Candidate], dict, dict, dict]:
        o, log, progress = self.options, self.log, self.progress
        todo, skipped = [], {}
        for cls in self.pool:
            if cls.name in self.present_names:
                continue
            why = cls(log).applicable(log)
            if why:
                skipped[cls.name] = why
            else:
                todo.append(cls)
        members = [m for cls in todo for m in family_members(cls)]
        if progress is not None:
            progress.stage("candidates", len(members) + 1, unit="fits")
        # the score test screens at the refit; the base every candidate is scored against (the same warm-started
        # procedure, nothing added) is fitted beside them, last, where it fills a worker the others left idle
        floor = predicted_floor(self.fit.problem, self.fit.state) if o.screen_share > 0 else None
        *fitted, self.base = parallel(
            [(fit_member, (log, self.fit, self.fit, spec(m), o, floor)) for m in members]
            + [(effect_fit.likeliest, (log, self.fit.model, self.fit.poses, self.present, None,
                                       o.candidate_rounds, o.candidate_iterations))], self.workers, progress,
            self.client)
        fitted = [scored(f, self.base.log_likelihood) for f in fitted]
        keep = best_of_family([c for c, _, _ in fitted])      # a family's members compete; BIC keeps one
        fitted, members = [fitted[i] for i in keep], [members[i] for i in keep]
        self.settle_leaders(fitted, members)
        cands = [c for c, _, _ in fitted]
        explains = {cls.name: cls.explains for cls in self.pool}
        heldout_rounds(log, self.base, fitted, members, built_for(strong_structures(structure, o), explains),
                       self.workers, progress, self.client, o)
        cands.sort(key=lambda c: (c.delta_bic, -c.heldout_nll_drop))
        self.base_prediction = predicted_sightings(self.base.problem, self.base.state)
        return cands, skipped, explains, {cls.name: cls.distinguished_by for cls in self.pool}

    def settle_leaders(self, fitted: list, members: list) -> None:
        """When two or more fitted candidates lead (delta BIC at most ``bic_support`` and at least ``lookalike_gain``
        of the best's), they and the base go on from their fits to the leaders' rounds in all
        (``options.leaders_settle``) and the leaders are scored against that base (``fitted`` updated in place; the
        base, and what the proposal is scored against, becomes it). An effect whose optimum lies away from the
        base's poses (a camera latency: the poses must move back) needs more rounds to reach it than a look-alike
        whose optimum is near (an actuator lag)."""
        o = self.options
        rounds = o.leaders_settle(self.kind)
        if rounds <= o.candidate_rounds:
            return
        lead = leading([c for c, m, _ in fitted if m is not None], o)      # the fitted ones (screened have no fit)
        leaders = [i for i, (c, _, _) in enumerate(fitted) if any(c is d for d in lead)]
        if len(leaders) < 2:
            return
        if self.progress is not None:
            self.progress.stage("settling the leaders", len(leaders) + 1, unit="fits")
        more = replace(o, candidate_rounds=rounds - o.candidate_rounds)
        self.options = replace(o, candidate_rounds=rounds)      # a proposal, fitted from the start
        *again, self.base = parallel(
            [(fit_member, (self.log, self.fit, self.base, spec(members[i]), more, None, fitted[i][1:]))
             for i in leaders]
            + [(effect_fit.likeliest, (self.log, self.base.model, self.base.poses, self.present, None,
                                       more.candidate_rounds, o.candidate_iterations))], self.workers, self.progress,
            self.client)
        again = [scored(a, self.base.log_likelihood) for a in again]
        for i, (c, m, p) in zip(leaders, again):
            old = fitted[i][0]
            if old.orders:
                c.orders = {**old.orders, c.order: c.delta_bic}
            fitted[i] = (c, m, p)

    def challenge(self, cls) -> tuple[float, float]:
        c = fit_candidate(self.log, self.fit, self.base, cls, self.options)[0]
        return c.delta_log_likelihood, c.delta_bic
