"""A command map's candidates, on the command-model graph of :mod:`casm_graph.fit.continuous`: the model is
re-settled on the log (poses, command map and polynomial; noise levels as given), the catalog effects these
graphs can take (``continuous.EFFECTS``) are the candidates, the delays placed by their profile
(:func:`casm_graph.fit.continuous.profile`), the others fitted through their hooks, and every one scored by delta
BIC against one base, each settled the same way at its value. Time-blocked held-out folds are not run for these,
so the verdict's second line of evidence is the residual structure the effect is built for (a covariate's bins,
or the sparse regression's terms). Noise-only candidates (false detections, range-dependent noise) are scored at
the base's poses, with held-out folds (:func:`noise_candidate`).
"""
from __future__ import annotations

from dataclasses import replace
from functools import cached_property, partial

import numpy as np

from casm_graph.analysis.candidates.base import Bench
from casm_graph.analysis.candidates.pool import call, parallel
from casm_graph.analysis.diagnosis import (DEFAULTS, NO_FOLDS, Candidate, DiagnoseOptions, best_of_family,
                                           channel_report, chosen_candidates, family_best, family_members, folds,
                                           leading, predicted_sightings, standardised)
from casm_graph.fit import continuous as CT
from casm_graph.fit.residuals import channels, sighting_leverage, sighting_residuals
from casm_graph.fit.result import Fit
from casm_graph.fit.solve import least_squares
from casm_graph.graph import augmented
from casm_graph.graph.problem import Problem
from casm_graph.io.log import Log, LogError
from casm_graph.models.effects import REGISTRY, unphysical
from casm_graph.models.effects.false_detections import FalseDetections, mixture_terms, reading_span, share
from casm_graph.models.model import Model

WHAT = {"actuator_lag": "For continuous commands: the velocity follows the command map through a lag of mean delay "
                        "{:.3f} s ({} first-order stage{})."}


def settled(log: Log, lay, model: Model, use, start: np.ndarray, effects, rounds: int, iterations: int) -> tuple:
    """(log-likelihood, model, the sightings it predicts) of ``model`` with ``effects`` settled on the coarse graph
    ``lay`` from knot poses ``start`` (:func:`casm_graph.fit.continuous.settled_log_likelihood`): a worker's task."""
    ll, m, pb, st = CT.settled_log_likelihood(log, lay, model, use, start, effects, rounds=rounds,
                                              iterations=iterations)
    return ll, m, predicted_sightings(pb, st)


def settled_hooked(log: Log, lay, model: Model, poses: np.ndarray, use, start: np.ndarray, own, e, rounds: int,
                   iterations: int) -> tuple:
    """:func:`settled` with the hooked effect ``e`` added, started from ``poses`` (T+1, 3) as a fit starts it."""
    augmented.begin([e], model, poses)
    return settled(log, lay, model, use, start, [*own, e], rounds, iterations)


def settled_profiled(log: Log, fit: Fit, name: str, own, search, knot_dt: float, lay, use, start: np.ndarray,
                     rounds: int) -> tuple:
    """A profiled effect's candidate: its profile (:func:`casm_graph.fit.continuous.profile`) on the coarse graph,
    the model with it at its maximum, and that model :func:`settled`."""
    prof = CT.profile(log, fit, name, own, options=search, knot_dt=knot_dt)
    lagged = CT.with_effect(fit.model, name, prof.value, prof.order)
    return (prof, lagged) + settled(log, lay, lagged, use, start, own, rounds, search.iterations)


def calibrated_member(log: Log, base: Fit, e, options: CT.CommandGraphOptions, noise_ratio=None
                      ) -> tuple[float, str]:
    """The log-likelihood ``calibrate --effect`` reaches from ``base`` with the family member ``e`` (a fresh
    instance: its start is placed from ``base``'s poses), and why its fit cannot happen ("" when it can): a worker's
    task. ``noise_ratio``: the motion noise levels with the member over those without, on the coarse graph; the
    fit starts from ``base``'s times them (the motion noise is a fixed point the rounds reach slowly: on an omni
    carpet 30 % of the confirmation's time saved, each member a little higher than from ``base``'s)."""
    if noise_ratio is not None:
        base = replace(base, model=base.model.with_(motion_noise=base.model.motion_noise * noise_ratio))
    fit = CT.fit_hooked(log, base, [type(e)(log)], marginals=False, options=options)
    return fit.log_likelihood, unphysical(type(e), fit.model.effects.get(e.name, {}), log) or ""


def hooked_candidates(log: Log, model: Model, extra_effects=()) -> tuple[list, dict]:
    """Effects fitted through their hooks that may be tried on ``log`` (catalog and ``extra_effects``, not in the
    model yet), and the others with the reason each is skipped."""
    tried, skipped = [], {}
    classes = {**{n: c for n, c in REGISTRY.items() if n not in CT.EFFECTS}, **{c.name: c for c in extra_effects}}
    for name, cls in sorted(classes.items()):
        if name in model.effects:
            continue
        if name in CT.NOISE_EFFECTS:
            skipped[name] = "added on request (calibrate --effect), not diagnosed"
            continue
        try:
            CT.check_effects([cls], log)
        except LogError as err:
            skipped[name] = str(err).split(": ", 1)[-1]
            continue
        tried.extend(m(log) for m in family_members(cls))
    return tried, skipped


def mixture_share(reading: np.ndarray, bearing: np.ndarray, reading_sigma, bearing_sigma: float, span: float,
                  iterations: int = 200, tol: float = 1e-7) -> float:
    """The false-detection share that maximises the mixture's likelihood of these residuals (sigmas held), by EM."""
    f = FalseDetections.start[0]
    for _ in range(iterations):
        w = mixture_terms(reading, bearing, reading_sigma, bearing_sigma, f, span)["weight"]
        new = share(w) if len(w) else f
        if abs(new - f) < tol:
            return new
        f = new
    return f


def noise_candidate(log: Log, model: Model, poses: np.ndarray, effects: list, effect, use: tuple, n: int,
                    options: DiagnoseOptions = DEFAULTS, leverage: np.ndarray | None = None) -> Candidate:
    """A noise-only ``effect`` scored at the base's poses (T+1, 3), which a noise model does not move: its
    parameters from the sightings' residuals, its log-likelihood against the base's on the same sightings, and
    on ``options.folds`` time blocks the parameters learned from the others scoring each block. A false-detection
    mixture is scored on every sighting, the ones the gate sets aside too (their number and size are its
    evidence), the base's sigmas held; an effect that scales the readings' sigma on the readings the gate kept
    (``use``), the reading sigma concentrated out of both, on the residuals standardised by their ``leverage`` (per
    observation, :func:`casm_graph.fit.residuals.sighting_leverage`): a near sighting on a steep curve pins its
    pose and keeps a small residual, which read raw as noise growing with distance (an omni world's constant camera
    noise after a friction patch was added). A refit of the poses would let them trade motion residuals for
    sighting residuals, which confounds the comparison of two noise models (BENCHMARKS.md)."""
    res = sighting_residuals(log, poses[log.obs_step], model, effects)
    noisy = [(e, s) for e, s in zip(effects, augmented.parameter_slices(list(effects))) if e.noise_only]
    scale = augmented.reading_scale(noisy, augmented.theta_from_model(list(effects), model), res["distance"])
    rr, rb, d = res["reading"], res["bearing_residual"], res["distance"]
    if effect.mixture:
        rows = np.isfinite(log.obs_reading) | np.isfinite(log.obs_bearing)
        span = reading_span(log.obs_reading)
        sr, sb = model.reading_sigma * scale, model.bearing_sigma

        def fit(sel):
            return mixture_share(rr[sel], rb[sel], sr[sel], sb, span)

        def gain(sel, f):
            m = mixture_terms(rr[sel], rb[sel], sr[sel], sb, f, span)
            return m["log_density"] - m["gaussian"]

        def described(f):
            return effect.describe(np.array([f]))
    else:
        rows = use[0] & np.isfinite(rr)
        z = standardised(rr, leverage) / scale     # in units of the reading sigma, the base's own scales out

        def fit(sel):
            th = effect.estimate_noise(np.asarray(effect.start, float), z[sel], None, d[sel],
                                       {"weight": np.ones(int(sel.sum())), "reading_scale": np.ones(int(sel.sum()))})
            s1 = effect.reading_scale(th, d, {})
            return th, s1, np.mean(z[sel] ** 2), np.mean((z[sel] / s1[sel]) ** 2)

        def gain(sel, p):
            _, s1, v0, v1 = p
            return (-0.5 * (z[sel] / s1[sel]) ** 2 / v1 - 0.5 * np.log(v1) - np.log(s1[sel])
                    + 0.5 * z[sel] ** 2 / v0 + 0.5 * np.log(v0))

        def described(p):
            return effect.describe(p[0])
    p = fit(rows)
    dll = float(np.sum(gain(rows, p)))
    heldout = sum(float(np.sum(gain(rows & ~train, fit(rows & train)))) for train in folds(log, options.folds))
    return Candidate(effect=effect.name, channel=effect.channel,
                     delta_bic=-2 * dll + effect.free_parameters() * np.log(n), heldout_nll_drop=float(heldout),
                     explanation=effect.physics, delta_log_likelihood=dll, parameters=described(p), heldout_skipped="")


def refitted(log: Log, model: Model, effects, lay, use, poses: np.ndarray, iterations: int) -> tuple:
    """(the fine graph's problem, its state after ``iterations`` LM iterations) for ``model`` with ``effects`` on
    the layout ``lay`` and gate ``use``, started from ``poses`` (every step's): the base's refit and a candidate's
    on the same footing."""
    problem = Problem(log, model, effects, lay=lay, gate=use, poses=poses[lay.knots])
    st, _ = least_squares(problem, problem.state(poses[lay.knots], model), max_iterations=iterations)
    return problem, st


class CommandBench(Bench):
    """The candidates of a continuous-command log, settled on the coarse graph against one base settled alike.

    Each candidate is settled in ``options.candidate_rounds`` rounds (a latency's velocity window follows its delay
    from one to the next). With the leaders' rounds above that (off by default), the leaders (the candidates
    a verdict or a look-alike group could name) and the base are then settled until their log-likelihoods stop
    moving: an effect whose optimum lies away from the base's poses needs more rounds to reach it than one whose
    optimum is near. The base, the profiles and the hooked effects settle side by side on ``workers`` processes or
    a Dask ``client`` (:mod:`casm_graph.analysis.candidates.pool`). The knot spacings are the calibration's
    (``calibrated.command_graph``), else the model's own (:func:`casm_graph.fit.continuous.options_of`)."""

    kind = "command_poly"

    def __init__(self, log: Log, model: Model, poses: np.ndarray, options: DiagnoseOptions = DEFAULTS,
                 extra_effects=(), candidates=None, workers: int = 2, client=None, progress=None, calibrated=None):
        super().__init__(log, model, poses, options)
        o = options
        self.extra_effects, self.progress, self.workers, self.client = extra_effects, progress, workers, client
        graph = calibrated.command_graph if calibrated is not None else CT.options_of(model)
        self.graph = graph
        self.coarse_fits = {}            # id of a hooked candidate -> its model settled on the coarse graph
        self.with_candidate = {}         # id of a candidate -> the base's model with its effect fitted, its effects
        self.search = replace(graph.profile, lag_order_support=o.lag_order_support)    # the diagnosis's own support
        self.chosen = chosen_candidates(candidates, extra_effects)
        if progress is not None:
            progress.stage("refit model", None)
        self.own = own = CT.hooked_effects(log, model, extra_effects)
        lay = CT.layout(log, graph.full_knot_dt)
        use = CT.gate(log, poses[log.obs_step], model, effects=own)
        problem, st = refitted(log, model, own, lay, use, poses, o.candidate_iterations)
        self.model = model = problem.with_state(model, st)
        full = CT.fill_in(log, model, lay.knots, st.poses)
        self.fit = Fit(model=model, poses=full, pose_std=np.full_like(full, np.nan), log_likelihood=-problem.cost(st))
        self.problem, self.state, self.poses, self.use = problem, st, full, use
        self.set_aside = problem.set_aside(model)
        self.coarse = CT.layout(log, graph.coarse_knot_dt)
        self.cuse = CT.gate(log, full[log.obs_step], model, effects=own)
        self.start = full[self.coarse.knots]
        self.n = CT.residual_rows(log, self.coarse, self.cuse)
        self.rounds, self.ll0 = o.candidate_rounds, None

    @cached_property
    def leverage(self) -> np.ndarray | None:
        """Each reading's leverage on the refitted graph (NaN where it has none), for the noise candidates."""
        return sighting_leverage(self.problem, self.state).get("reading")

    def wanted(self, name: str) -> bool:
        return self.chosen is None or name in self.chosen

    def settle_base(self, rounds: int) -> tuple:
        """The base's task: (:func:`settled`, its arguments)."""
        return settled, (self.log, self.coarse, self.model, self.cuse, self.start, self.own, rounds,
                         self.search.iterations)

    def settle_hooked(self, rounds: int, e) -> tuple:
        """A hooked effect's candidate (the proposal's too), settled as the base is: (:func:`settled_hooked`, its
        arguments)."""
        return settled_hooked, (self.log, self.coarse, self.model, self.poses, self.cuse, self.start, self.own, e,
                                rounds, self.search.iterations)

    def profile_task(self, name: str, rounds: int) -> tuple:
        """A profiled effect's candidate, its profile then the model at its maximum settled as the base is:
        (:func:`settled_profiled`, its arguments)."""
        return settled_profiled, (self.log, self.fit, name, self.own, self.search, self.graph.coarse_knot_dt,
                                  self.coarse, self.cuse, self.start, rounds)

    def settle_profiled(self, rounds: int, lagged: Model) -> tuple:
        """A profiled effect's model, settled again: (:func:`settled`, its arguments)."""
        return settled, (self.log, self.coarse, lagged, self.cuse, self.start, self.own, rounds,
                         self.search.iterations)

    def score(self, structure: list[dict]) -> tuple[list[Candidate], dict, dict, dict]:
        o, log, model, progress, n = self.options, self.log, self.model, self.progress, self.n
        hooked, skipped = hooked_candidates(log, model, self.extra_effects)
        cands = []
        hooked = [e for e in hooked if self.wanted(e.name)]
        todo = [m for m in CT.EFFECTS if CT.effect_value(model, m) == 0 and m not in skipped and self.wanted(m)]
        fitted = [e for e in hooked if not e.noise_only]
        if progress is not None and todo + hooked:
            progress.stage("candidates", 1 + len(todo) + len(hooked), unit="fits")
        settles = {}              # candidate -> how to settle it again, for the leaders' decision
        if todo or hooked:        # every candidate scored against one base, settled as they are, side by side
            done = parallel([self.settle_base(o.candidate_rounds)]
                            + [self.profile_task(name, o.candidate_rounds) for name in todo]
                            + [self.settle_hooked(o.candidate_rounds, e) for e in fitted],
                            self.workers, progress, self.client)
            self.ll0, self.coarse_base, self.base_prediction = done[0]
            profiled, settled_fits = done[1:1 + len(todo)], iter(done[1 + len(todo):])
            for name, (prof, lagged, ll, _, prediction) in zip(todo, profiled):
                gain = float(ll - self.ll0)
                eff = REGISTRY[name]
                (param,) = eff.params
                what = WHAT[name].format(prof.value, prof.order, "s" if prof.order > 1 else "")
                cands.append(Candidate(effect=name, channel=eff.channel,
                                       delta_bic=-2 * gain + prof.order * np.log(n),
                                       heldout_nll_drop=float("nan"), explanation=f"{what} {eff.physics}",
                                       delta_log_likelihood=gain,
                                       parameters={param: prof.value,
                                                   **({"order": prof.order} if prof.order > 1 else {})},
                                       heldout_skipped=NO_FOLDS, prediction=prediction))
                settles[id(cands[-1])] = (partial(self.settle_profiled, lagged=lagged), prof.order)
                self.with_candidate[id(cands[-1])] = (lagged, self.own)
            for e in hooked:
                if e.noise_only:                  # scored at the base's poses, without a refit
                    cands.append(noise_candidate(log, model, self.poses, self.own, e, self.cuse, n, o,
                                                 self.leverage))
                    if progress is not None:
                        progress.step(1)
                    continue
                ll, m, prediction = next(settled_fits)
                gain = float(ll - self.ll0)
                entry = dict(m.effects.get(e.name, {}))
                cands.append(Candidate(effect=e.name, channel=e.channel,
                                       delta_bic=-2 * gain + e.free_parameters() * np.log(n),
                                       heldout_nll_drop=float("nan"), explanation=e.physics,
                                       delta_log_likelihood=gain, parameters=entry,
                                       order=e.order if e.orders else None, heldout_skipped=NO_FOLDS,
                                       prediction=prediction, implausible=unphysical(type(e), entry, log) or ""))
                settles[id(cands[-1])] = (partial(self.settle_hooked, e=e), e.free_parameters())
                self.coarse_fits[id(cands[-1])] = m
                self.with_candidate[id(cands[-1])] = (model.with_(effects={**model.effects, e.name: entry}),
                                                      [*self.own, e])
        cands = [cands[i] for i in best_of_family(cands, self.confirm(cands, fitted))]   # BIC keeps one member
        cands.sort(key=lambda c: c.delta_bic)
        self.decide(cands, settles)
        names = [*(m for m in CT.EFFECTS if m not in skipped and self.wanted(m)), *(e.name for e in hooked)]
        kinds = {**REGISTRY, **{e.name: type(e) for e in hooked}}
        self.last = tuple(e.name for e in hooked if e.mixture)
        return (cands, skipped, {m: kinds[m].explains for m in names},
                {m: kinds[m].distinguished_by for m in names})

    def confirm(self, cands: list[Candidate], fitted: list) -> dict:
        """{family: order} for each leading family (``options.confirm_members``) whose members within
        ``options.lookalike_gain`` of its best gain on the coarse graph are more than one: each fitted as
        ``calibrate --effect`` fits it, on the fine graph from the refitted base, the one with the best BIC there
        kept (its log-likelihood by order in ``Candidate.confirmed``)."""
        o = self.options
        if not o.confirm_members:
            return {}
        best = [cands[i] for i in family_best(cands)]
        effects = {(e.name, e.order): e for e in fitted}
        todo = {}
        for lead in leading(best, o):
            members = [c for c in cands if c.effect == lead.effect and (c.effect, c.order) in effects
                       and c.delta_bic <= o.bic_support and c.delta_bic <= o.lookalike_gain * lead.delta_bic]
            if len(members) > 1:
                todo[lead.effect] = members
        if not todo:
            return {}
        work = [(c, effects[(c.effect, c.order)]) for members in todo.values() for c in members]
        if self.progress is not None:
            self.progress.stage("confirming members", len(work), unit="fits")
        lls = parallel([(calibrated_member, (self.log, self.fit, e, self.graph, self.noise_ratio(c)))
                        for c, e in work], self.workers,
                       self.progress, self.client)
        n = CT.residual_rows(self.log, self.problem.lay, self.use)
        chosen = {}
        for name, members in todo.items():
            scored = {c.order: (ll, e.free_parameters(), why)
                      for (c, e), (ll, why) in zip(work, lls) if c.effect == name}
            keep = min(scored, key=lambda k: (bool(scored[k][2]), -2 * scored[k][0] + scored[k][1] * np.log(n)))
            chosen[name] = keep
            for c in members:
                c.confirmed = {k: float(v[0]) for k, v in sorted(scored.items())}
                if c.order == keep and scored[keep][2]:
                    c.implausible = scored[keep][2]      # as calibrate would fit it
        return chosen

    def noise_ratio(self, c: Candidate) -> np.ndarray:
        """Candidate ``c``'s motion noise levels over the base's, both settled on the coarse graph (1 where
        the base's is zero)."""
        with_c = np.asarray(self.coarse_fits[id(c)].motion_noise, float)
        without = np.asarray(self.coarse_base.motion_noise, float)
        return np.divide(with_c, without, out=np.ones_like(with_c), where=without > 0)

    def decide(self, cands: list[Candidate], settles: dict) -> None:
        """With the leaders' rounds (``options.leaders_settle``) above the candidates', the leaders and the base
        settled again for up to that many rounds and re-scored (``cands`` re-sorted in place)."""
        o, n = self.options, self.n
        rounds = o.leaders_settle(self.kind)
        leaders = [c for c in leading(cands, o) if id(c) in settles]
        if len(leaders) <= 1 or rounds <= o.candidate_rounds:
            return
        self.rounds = rounds
        if self.progress is not None:
            self.progress.stage("settling the leaders", len(leaders) + 1, unit="fits")
        done = parallel([self.settle_base(rounds)] + [settles[id(c)][0](rounds) for c in leaders],
                        self.workers, self.progress, self.client)
        self.ll0, _, self.base_prediction = done[0]
        for c, (ll, m, prediction) in zip(leaders, done[1:]):
            c.parameters = dict(m.effects.get(c.effect, c.parameters))    # a hooked effect's moved with the rounds
            if c.effect in m.effects:
                with_c, effects = self.with_candidate[id(c)]
                self.with_candidate[id(c)] = (with_c.with_(effects={**with_c.effects, c.effect: c.parameters}), effects)
            c.delta_log_likelihood = float(ll - self.ll0)
            c.delta_bic = -2 * c.delta_log_likelihood + settles[id(c)][1] * np.log(n)
            c.prediction = prediction
        cands.sort(key=lambda c: c.delta_bic)

    def refit_report(self, c: Candidate) -> dict | None:
        """The channel report of the base's model with ``c``'s fitted effect, its noise levels the base's, refitted on
        the base's graph from its poses: the base's report and this one differ by the effect alone."""
        if id(c) not in self.with_candidate:
            return None
        if self.progress is not None:
            self.progress.stage(f"refit with {c.effect}", None)
        model, effects = self.with_candidate[id(c)]
        problem, st = refitted(self.log, model, effects, self.problem.lay, self.use, self.poses,
                               self.options.candidate_iterations)
        return channel_report(channels(problem, st, self.options.command_change), self.options)

    def challenge(self, cls) -> tuple[float, float]:
        """The proposal, settled as a hooked candidate against the same base."""
        e = cls(self.log)
        gain = float(call(self.settle_hooked(self.rounds, e))[0] - self.ll0)
        return gain, -2 * gain + e.free_parameters() * np.log(self.n)

    @property
    def relative(self) -> float:
        return self.options.lookalike_relative

    def advice(self, proposal: dict) -> list[str]:
        """A turn rate in proportion to the forward speed is the turn map's term in v, which a calibration without
        it can fit (``--cross-terms``)."""
        cm = self.model.command
        terms = proposal.get("terms", {}) if proposal else {}
        if cm.cross or cm.with_cross() is cm or not {"turn: v_forward", "turn: speed"} & set(terms):
            return []
        tried = (self.model.fit or {}).get("cross_term")
        why = (f"the calibration tried it and left it out (delta BIC {tried['delta_bic']:,.1f})" if tried else
               "this calibration was made without it")
        return [f"A turn rate in proportion to the forward speed is the coupling of a differential drive's unequal "
                f"wheels, which the turn map's term in v holds: `calibrate --cross-terms on` fits it in the action "
                f"model ({why})."]

    def notes(self, candidates: list[Candidate]) -> list[str]:
        if not candidates:
            return []
        return ["On continuous-command logs held-out folds score only the noise candidates (at the base's poses); "
                "the others need BIC and the residual structure they are built for."]
