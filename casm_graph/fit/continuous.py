"""Calibration of a log with continuous commands: poses, command-model parameters and sensor polynomial.

The graph is the one graph problem (:class:`casm_graph.graph.problem.Problem`) with the command-map
action part (:mod:`casm_graph.graph.actions.command_poly`): a pose at a set of knots (every ``knot_dt``
seconds and at every step with an observation, so sightings attach to their own pose exactly), the
command model of :mod:`casm_graph.models.command_model` and the sensor polynomial in its parameter vector.

The start is global (:mod:`casm_graph.fit.windows`): the sensor hypothesis from the grid smoother of
:func:`casm_graph.fit.locate.locate`, the command maps at the nominal velocity = command, and each
window of sightings placed along its dead-reckoned path at every candidate heading, the headings
chained across windows. Then a coarse graph (1 s knots) is optimised in rounds that re-estimate every noise level and set
aside sightings more than ``robust.GATE`` sigmas off, its first rounds with the nominal maps and the
polynomial held (the sightings place the poses before the maps may move), and a finer graph
(0.25 s knots) finishes.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from functools import partial

import numpy as np
from scipy.optimize import minimize_scalar
from gtsam.symbol_shorthand import X

from casm_graph.fit import turns
from casm_graph.fit import windows as W
from casm_graph.fit.residuals import distances, sighting_residuals
from casm_graph.fit.result import Fit, Progress
from casm_graph.fit.sensor_degree import SensorCurveOptions, better_curve, choose_curve, near_curve, suspect
from casm_graph.fit.solve import RIDGE_WARNING, chain_marginals, least_squares, world_std
from casm_graph.graph import augmented, robust
from casm_graph.graph import table as G
from casm_graph.graph.actions.command_poly import Layout, layout
from casm_graph.graph.problem import THETA, Problem, State
from casm_graph.io.log import Log, LogError
from casm_graph.models.command_model import COMMANDS, for_commands
from casm_graph.models.effects import of_model
from casm_graph.models.effects import regional_motion_noise as RMN
from casm_graph.models.model import PAPER_MOTION_NOISE, PAPER_START_BEARING_SIGMA, PAPER_START_READING_SIGMA, Model
from factors.reading import fit_curve

MIN_SIGHTINGS = 10
INIT_WINDOW = 5.0            # s: the shortest log the start's windows can place


@dataclass(frozen=True)
class ProfileOptions:
    """How a profiled effect's parameter (the command model's lag) is searched on the coarse
    graph (:func:`profile`): a grid brackets the maximum, Brent's bounded search refines it."""

    grid: dict = field(default_factory=lambda: {"actuator_lag": (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.8)})   # tau, s
    bounds: dict = field(default_factory=lambda: {"actuator_lag": (0.0, 2.0)})
    tol: dict = field(default_factory=lambda: {"actuator_lag": 0.01})
    iterations: int = 8                # LM iterations settling each evaluation (half as many after the noise step)
    lag_orders: tuple = (1, 2)         # the lag's family: one first-order stage, or two (a critically damped drive),
    lag_order_support: float = -10.0   # the second tried when the first is this supported (delta BIC), kept when
    #                                    BIC prefers it

    def to_json(self) -> dict:
        """As model.json records it (lists for tuples)."""
        return {"grid": {k: list(v) for k, v in self.grid.items()}, "bounds": {k: list(v) for k, v in self.bounds.items()},
                "tol": dict(self.tol), "iterations": self.iterations, "lag_orders": list(self.lag_orders),
                "lag_order_support": self.lag_order_support}


@dataclass(frozen=True)
class CommandGraphOptions:
    """How the command-model graph searches (the module docstring's coarse and fine stages); recorded in model.json
    ``fit.options.command_graph``."""

    coarse_knot_dt: float = 1.0        # s between the coarse graph's knots
    coarse_held_rounds: int = 3        # coarse rounds with the maps held first: freed on the initialiser's poses, MRCLAM
    #                                    robot 4 (fewest sightings) ran to a speed map 131 % off (log-likelihood 22,036;
    #                                    42,665 this way)
    coarse_rounds: int = 5             # free coarse rounds, each LM then the noise step
    coarse_iterations: int = 8         # LM iterations per coarse round
    full_knot_dt: float = 0.25         # s between the fine graph's knots
    full_rounds: int = 2               # fine rounds
    full_iterations: int = 15          # LM iterations per fine round
    full_settle: int = 6               # more fine rounds, at most, until no noise level moves by ``noise_tol``
    noise_tol: float = 0.02
    regional_rounds: int = 40          # EM rounds of regional_motion_noise's k's on the fine graph; stop when none moves
    regional_tol: float = 0.02         # by this share (slow where sightings say little about single steps)
    hooked_rounds: int = 3             # fine rounds with hooked effects' parameters free (then up to ``full_settle`` more)
    cross_margin: float = 10.0         # calibrate's cross_terms "auto": the turn map's term in v kept when its delta
    #                                    BIC is at most minus this (strong evidence on Kass and Raftery's scale)
    profile: ProfileOptions = field(default_factory=ProfileOptions)   # the lag's search
    sensor_curve: SensorCurveOptions = field(default_factory=SensorCurveOptions)   # when the data move the curve

    def to_json(self) -> dict:
        return {**asdict(self), "profile": self.profile.to_json()}


DEFAULTS = CommandGraphOptions()


def options_of(model: Model) -> CommandGraphOptions:
    """The graph options ``model`` was calibrated with (model.json ``fit.options.command_graph``, else its
    ``fit.knot_dt``; defaults for what is not recorded), so a diagnosis, the uncertainty and the ground-truth
    check rebuild the calibration's graph."""
    fit = model.fit or {}
    recorded = dict(((fit.get("options") or {}).get("command_graph") or {}))
    if "knot_dt" in fit:
        recorded.setdefault("full_knot_dt", fit["knot_dt"])
    known = {}
    for k, v in recorded.items():
        if k not in CommandGraphOptions.__dataclass_fields__ or isinstance(getattr(DEFAULTS, k),
                                                                             (ProfileOptions, SensorCurveOptions)):
            continue                    # the profile's search and the curve's choice are not part of the graph
        spacing = k.endswith("_dt")     # a knot spacing must be positive, a count or tolerance non-negative
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0 or (spacing and v == 0):
            raise LogError(f"model.json: fit.options.command_graph.{k} must be a "
                           f"{'positive' if spacing else 'non-negative'} number (got {v!r})")
        known[k] = type(getattr(DEFAULTS, k))(v)
    return replace(DEFAULTS, **known)


def gate(log: Log, poses_at_obs: np.ndarray, model: Model, z: float = robust.GATE,
         effects=()) -> tuple[np.ndarray, np.ndarray]:
    """(reading, bearing) masks of the sightings within ``z`` sigmas of the model's prediction."""
    res = sighting_residuals(log, poses_at_obs, model, effects)
    noisy = [(e, s) for e, s in zip(effects, augmented.parameter_slices(list(effects))) if e.noise_only]
    theta = augmented.theta_from_model(list(effects), model) if noisy else np.zeros(0)
    scale = augmented.reading_scale(noisy, theta, res["distance"])   # the noise effects' factor on each sigma
    r = np.abs(res["reading"]) / (model.reading_sigma * scale)
    b = np.abs(res["bearing_residual"]) / model.bearing_sigma
    return ~(r > z), ~(b > z)


def dead_reckon(controls: np.ndarray, dt: np.ndarray, model: Model, start: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses integrating the command model from ``start``, each step along the model's step heading."""
    return W.dead_reckon_steps(model.command.velocities(controls, dt), dt, start, model.command.lead)


def fill_in(log: Log, model: Model, knots: np.ndarray, knot_poses: np.ndarray) -> np.ndarray:
    """(T+1, 3) poses: each knot-to-knot stretch dead-reckoned, its closure error spread linearly."""
    return G.fill_between(knots, knot_poses, model.step_displacements(log))


# --------------------------------------------------------------------------- global start

def initialise(log: Log, model: Model, options: W.WindowOptions | None = None) -> W.WindowStart:
    """Global start from nothing but the log and the map (:func:`casm_graph.fit.windows.window_start`).

    The command maps start at the nominal velocity = command (the robot's own commands are the only
    velocity scale in the log); the graph learns them. The start's model carries that map and the
    start's sensor curve.
    """
    nominal = model.command.same_form(log.controls)
    v = nominal.velocities(log.controls, log.dt)
    speed = 2.0 * float(np.max(np.hypot(v[:, 0], v[:, 1])))   # random walk faster than any commanded speed
    ws = W.window_start(log, v, len(model.reading_poly), max(speed, 0.05), options)
    return W.with_model(ws, model.with_(command=nominal), log)


# --------------------------------------------------------------------------- the fit

def start_model(log: Log, sensor_degree: int = 3, v_degree: int = 2, w_degree: int = 1,
                basis: str = "distance", cross: bool = False, step_heading: str = "middle") -> Model:
    """The paper's start for continuous commands: zero velocity for every command, a flat sensor line; with
    ``cross`` the turn map of ``v, w`` also linear in ``v``; each step along the heading ``step_heading`` says.

    Either channel may be missing from the whole log (range-only or bearing-only sensors); the
    model then records which channels it has (``Model.channels``).
    """
    if log.controls is None or tuple(log.control_names) not in COMMANDS:
        raise LogError("commands.csv: the continuous-command model needs columns 'v,w' or 'vx,vy,w' "
                       f"(this log has {','.join(log.control_names) or 'action'})")
    n_r, n_b = int(np.sum(~np.isnan(log.obs_reading))), int(np.sum(~np.isnan(log.obs_bearing)))
    span = log.pose_times[-1] - log.pose_times[0]
    if max(n_r, n_b) < MIN_SIGHTINGS or span < INIT_WINDOW:
        raise LogError(f"observations.csv: {n_r} readings and {n_b} bearings over {span:.1f} s; calibrating "
                       f"continuous commands needs at least {MIN_SIGHTINGS} of one kind and {INIT_WINDOW:g} s "
                       f"(action-table logs need an 'action' column)")
    poly = np.zeros(sensor_degree + 1)
    poly[0] = float(np.nanmedian(log.obs_reading)) if n_r else 0.0
    return Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=poly,
                 reading_sigma=PAPER_START_READING_SIGMA, bearing_sigma=PAPER_START_BEARING_SIGMA,
                 motion_noise=np.array(PAPER_MOTION_NOISE),
                 command=for_commands(log.controls, v_degree, w_degree, cross=cross, step_heading=step_heading),
                 channels=log.channels, reading_basis=basis)


def identity_model(log: Log, like: Model) -> Model:
    """The uncalibrated models: actual velocity = command, reading = distance, no effects; noise levels of ``like``."""
    poly = np.zeros(len(like.reading_poly))
    poly[1] = 1.0
    cm = replace(like.command.same_form(log.controls), lag=0.0, lag_order=1)
    return like.with_(command=cm, reading_poly=poly, reading_basis="distance", effects={})


def noise_levels(model: Model) -> np.ndarray:
    """Every noise level of a model, for telling whether the noise step has settled."""
    return np.concatenate([[model.reading_sigma, model.bearing_sigma], np.asarray(model.motion_noise, float)])


def optimise_rounds(log: Log, lay: Layout, model: Model, poses: np.ndarray, rounds: int, iterations: int,
                    seed: int, label: str, trace: list, stages: list, progress: Progress,
                    freeze: bool = False, last_noise: bool = True, settle: int = 0, effects=(),
                    noise_tol: float = DEFAULTS.noise_tol):
    """Rounds of LM, each followed by gating of outliers and re-estimating the noise levels.

    With ``settle`` > 0, up to that many more rounds run until no noise level moves by more than
    ``noise_tol`` (the noise step is a fixed-point iteration, slow where the sightings' leverage is
    high: a floor log's bearing sigma stood at 1.5 x its truth after two rounds, at the truth after five).
    """
    use = None
    its, h = 0, None
    problem = st = None
    r = 0
    while r < rounds:
        problem = Problem(log, model, effects, lay=lay, gate=use, poses=poses)

        def tick(c):
            trace.append(c)
            stages.append(label)
            progress.step(0, cost=c)

        st, h = least_squares(problem, problem.state(poses, model), max_iterations=iterations, on_iteration=tick,
                              freeze_parameters=freeze)
        its += h.iterations
        st, h, more = turns.unspun(problem, st, h, partial(least_squares, problem, max_iterations=iterations,
                                                          on_iteration=tick, freeze_parameters=freeze))
        its += more
        poses = st.poses
        model = problem.with_state(model, st)
        if r < rounds - 1 or last_noise:
            before = noise_levels(model)
            model = augmented.estimate_noise(problem, st, model, seed=seed + r, poses_only=freeze)[0]
            use = gate(log, poses[lay.obs_knot], model, effects=effects)
            moved = float(np.max(np.abs(np.log(noise_levels(model) / before))))
            if settle > 0 and r == rounds - 2 and moved > noise_tol:
                rounds, settle = rounds + 1, settle - 1
        progress.step(1)
        r += 1
    return model, poses, problem, st, its, bool(h.converged)


def problem_log_likelihood(problem: "Problem", st, model: Model) -> float:
    """log p(data, knots | model) at ``st``: the cost with its Gaussian normalisers (noise levels fixed)."""
    if problem.mixed:       # every sighting, gated or not, by its mixture density; motion and priors as below
        rows = problem.rows(st, jacobians=False)
        ae, pe = rows.action_e, rows.prior_e
        return float(-0.5 * np.sum(ae ** 2) - 0.5 * np.sum(pe ** 2) - np.sum(np.log(problem.motion_sigma))
                     - 0.5 * ae.size * np.log(2 * np.pi)
                     + mixture_log_likelihood(problem, st))
    sel, n_motion = problem.r_sel, problem.motion_sigma.size
    log_det = (np.sum(np.log(problem.motion_sigma)) + sel.sum() * np.log(model.reading_sigma)
               + np.sum(np.log(problem.r_scale[problem.r_idx])) + problem.b_sel.sum() * np.log(model.bearing_sigma))
    n = n_motion + int(sel.sum()) + int(problem.b_sel.sum())
    return float(-problem.cost(st) - log_det - 0.5 * n * np.log(2 * np.pi))


def log_likelihood(log: Log, lay: Layout, model: Model, knot_poses: np.ndarray) -> float:
    """``problem_log_likelihood`` of a model and knot poses, sightings gated as a new round would gate them."""
    problem = Problem(log, model, lay=lay, gate=gate(log, knot_poses[lay.obs_knot], model), poses=knot_poses)
    return problem_log_likelihood(problem, problem.state(knot_poses, model), model)


def mixture_log_likelihood(problem: Problem, st: State) -> float:
    """Every measured sighting's log density under the problem's noise levels and noise effects (a
    false-detection mixture's), gated or not."""
    return float(np.sum(problem.observation_terms(st)["log_density"][problem.measured]))


@dataclass
class CoarseStart:
    """The global start settled on the coarse graph: model, poses at every step, and how it got there."""

    model: Model
    poses: np.ndarray                 # (T+1, 3)
    trace: list
    stages: list
    iterations: int
    starts: list                      # the window starts taken through the held rounds (best agreement first)
    held: list                        # the log-likelihood of each after the held rounds
    best: int                         # the one that went on


def coarse_start(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
                 start_options: W.WindowOptions | None = None, options: CommandGraphOptions = DEFAULTS) -> CoarseStart:
    """Global start (searched as ``start_options`` say), each candidate range slope through the held coarse
    rounds, the likeliest through the free coarse rounds: where ``fit`` and ``graph-em`` begin."""
    progress = progress or Progress()
    o = options
    trace, stages = [], []
    progress.stage("initialise", None)
    init = initialise(log, start, start_options or W.WindowOptions())
    noise = {"motion_noise": np.asarray(start.motion_noise, float), "bearing_sigma": float(start.bearing_sigma)}
    coarse = layout(log, o.coarse_knot_dt)
    starts = [init, *init.alternatives]
    progress.stage("coarse graph", len(starts) * o.coarse_held_rounds + o.coarse_rounds)
    held = []          # each start through the held rounds: (log-likelihood, model, knot poses, iterations, trace)
    for s in starts:
        t, g = [], []
        m, kp, _, _, its, _ = optimise_rounds(log, coarse, s.model.with_(**noise), s.poses[coarse.knots],
                                              o.coarse_held_rounds, o.coarse_iterations, seed, "coarse, maps held",
                                              t, g, progress, freeze=True, noise_tol=o.noise_tol)
        held.append((log_likelihood(log, coarse, m, kp), m, kp, its, (t, g)))
    best = max(range(len(held)), key=lambda i: held[i][0])
    _, model, kp, _, (t, g) = held[best]
    trace += t
    stages += g
    it0 = sum(h[3] for h in held)
    model, kp, _, _, it1, _ = optimise_rounds(log, coarse, model, kp, o.coarse_rounds, o.coarse_iterations, seed,
                                               "coarse", trace, stages, progress, noise_tol=o.noise_tol)
    return CoarseStart(model, fill_in(log, model, coarse.knots, kp), trace, stages, it0 + it1, starts,
                       [h[0] for h in held], best)


def fit(log: Log, start: Model | None = None, seed: int = 0, progress: Progress | None = None,
        marginals: bool = True, start_options: W.WindowOptions | None = None,
        options: CommandGraphOptions = DEFAULTS, max_sensor_degree: int = 0, free_basis: bool = False,
        try_cross: bool = False) -> Fit:
    """Calibrate a continuous-command log: global start (searched as ``start_options`` say), coarse graph in
    rounds, finer graph (as ``options`` say), marginals. ``max_sensor_degree``: the sensor polynomial's degree may
    rise to it when the data demand; ``free_basis``: when the fit in d shows a near-range misfit, a fit with the
    curve in 1/d competes (:mod:`casm_graph.fit.sensor_degree`, as on action tables); ``try_cross``: the turn
    map's term in v competes (:func:`cross_choice`)."""
    return fit_both_curves(log, start, seed, progress, marginals, start_options, options, max_sensor_degree,
                           free_basis, try_cross)[0]


def fit_both_curves(log: Log, start: Model | None = None, seed: int = 0, progress: Progress | None = None,
                    marginals: bool = True, start_options: W.WindowOptions | None = None,
                    options: CommandGraphOptions = DEFAULTS, max_sensor_degree: int = 0,
                    free_basis: bool = False, try_cross: bool = False) -> tuple[Fit, Fit | None]:
    """:func:`fit`, and the fit with the curve it passed over (None when one curve was fitted): effects on the
    sightings fitted later choose between the two again (:func:`curve_with_effects`)."""
    progress = progress or Progress()
    start = start or start_model(log)
    first = _fit(log, start, seed, progress, marginals, start_options, options, max_sensor_degree)
    if try_cross:
        first = cross_choice(log, first, seed, progress, marginals, options, max_sensor_degree)
    if not (free_basis and start.reading_basis == "distance" and suspect(first.model, log, options.sensor_curve)):
        return first, None
    progress.stage("the sensor curve in 1/d", None)
    other = in_basis(log, first, "inverse_distance", len(start.reading_poly) - 1, seed, progress, marginals, options,
                     max_sensor_degree)
    keep = better_curve(log, first, other, sighting_log_likelihood, options.sensor_curve)
    return keep, (other if keep is first else first)


def curve_in(log: Log, model: Model, poses: np.ndarray, basis: str, degree: int,
             tail: float = SensorCurveOptions.tail) -> Model:
    """``model`` with its sensor curve in ``basis``, of ``degree``, regressed on the readings at their distances
    from ``poses`` (T+1, 3), those within ``tail`` robust sigmas of ``model``'s own curve: a warm start in another
    basis."""
    ok = np.isfinite(log.obs_reading)
    d = distances(poses[log.obs_step], log)[ok]
    r = log.obs_reading[ok]
    keep = near_curve(r - model.reading(d), tail)
    return model.with_(reading_poly=fit_curve(d[keep], r[keep], degree, basis), reading_basis=basis)


def in_basis(log: Log, first: Fit, basis: str, degree: int, seed: int, progress: Progress, marginals: bool,
             o: CommandGraphOptions, max_sensor_degree: int) -> Fit:
    """``first`` refitted with its sensor curve in ``basis``: the curve of ``degree`` regressed on the readings at
    ``first``'s distances (those within ``o.sensor_curve.tail`` robust sigmas), then the fine graph from ``first``'s
    poses. Warm, unlike the action table's fresh start in 1/d: on continuous logs that start put a sighting on its
    landmark (0.05 m off, the standoff) on two of three omnidirectional worlds, 0.43 m from the truth on one."""
    t0 = time.perf_counter()
    model = curve_in(log, first.model, first.poses, basis, degree, o.sensor_curve.tail)
    return continued(first, _full_graph(log, model, first.poses, seed, progress, marginals, o, max_sensor_degree, [],
                                        [], 0, t0))


def continued(first: Fit, out: Fit) -> Fit:
    """``out``, a fit warm from ``first``'s poses, with ``first``'s records of how it started (and of the cross
    term's test) and their cost, stages, iterations, seconds and notes together."""
    out.model.fit.update({k: first.model.fit[k] for k in ("start_options", "start_slopes", "cross_term")
                          if k in first.model.fit}, iterations=first.iterations + out.iterations,
                         seconds=round(first.model.fit.get("seconds", 0) + out.model.fit["seconds"], 3))
    return replace(out, cost=first.cost + out.cost, stages=first.stages + out.stages,
                   iterations=first.iterations + out.iterations, notes={**first.notes, **out.notes})


def cross_choice(log: Log, first: Fit, seed: int, progress: Progress, marginals: bool, o: CommandGraphOptions,
                 max_sensor_degree: int) -> Fit:
    """``first`` refitted with the turn map's term in v (a differential drive's unequal wheels: turn rate += c v)
    when BIC supports it by ``o.cross_margin``, else ``first``: the fine graph warm from ``first``'s poses, its
    marginal std of the term giving the Wald statistic (c / std)^2, whose BIC is log n less, n the sightings plus
    three motion rows per knot. Not the two fits' likelihoods: the refit's extra rounds alone gained 177 nats on a
    wheel-world log whose term gained 27. Kept or not, ``fit.cross_term`` records the test."""
    cm = first.model.command
    if cm.cross or cm.with_cross() is cm:
        return first
    t0 = time.perf_counter()
    progress.stage("the turn map's term in v", None)
    model = first.model.with_(command=cm.with_cross())
    other = _full_graph(log, model, first.poses, seed, progress, True, o, max_sensor_degree, [], [], 0, t0)
    n = int(np.isfinite(log.obs_reading).sum() + np.isfinite(log.obs_bearing).sum()) + 3 * len(first.notes["knots"])
    value, std = other.model.command.cross_coefficient("w")
    wald = (value / std) ** 2 if std is not None and np.isfinite(std) and std > 0 else 0.0
    delta_bic = float(np.log(n) - wald)
    keep = continued(first, other) if delta_bic <= -o.cross_margin else first
    keep.model.fit["cross_term"] = {"kept": keep is not first, "delta_bic": round(delta_bic, 1), "wald": round(wald, 1),
                                    "w_per_v": round(value / cm.scale[0], 6),
                                    "w_per_v_std": None if std is None or not np.isfinite(std)
                                    else round(std / cm.scale[0], 6)}
    return keep


def sighting_log_likelihood(log: Log, fit: Fit, effects=()) -> float:
    """log p(data, knots | model) of ``fit`` at its poses and noise levels with every sighting in (none set aside,
    Huber's loss on the wild ones): fits that set aside different sightings scored on the same data. ``effects``
    (instances) act at the values ``fit.model`` records."""
    lay = layout(log, options_of(fit.model).full_knot_dt)
    kp = fit.poses[lay.knots]
    problem = Problem(log, fit.model, list(effects), lay=lay, poses=kp)
    return problem_log_likelihood(problem, problem.state(kp, fit.model), fit.model)


def _fit(log: Log, start: Model, seed: int, progress: Progress, marginals: bool,
         start_options: W.WindowOptions | None, o: CommandGraphOptions, max_sensor_degree: int) -> Fit:
    """One calibration from ``start`` (:func:`fit`'s arguments)."""
    t0 = time.perf_counter()
    start_options = start_options or W.WindowOptions()
    co = coarse_start(log, start, seed, progress, start_options, o)
    model, poses, trace, stages, it1 = co.model, co.poses, co.trace, co.stages, co.iterations
    full = layout(log, o.full_knot_dt)
    if RMN.RegionalMotionNoise.name in model.effects:
        progress.stage("regional noise", o.regional_rounds)
        for r in range(o.regional_rounds):
            before = RMN.from_entry(model.effects[RMN.RegionalMotionNoise.name])[1]
            model, kp, _, _, its, _ = optimise_rounds(log, full, model, poses[full.knots], 1, o.full_iterations,
                                                      seed + 200 + r, "regional", trace, stages, progress)
            it1 += its
            poses = fill_in(log, model, full.knots, kp)
            after = RMN.from_entry(model.effects[RMN.RegionalMotionNoise.name])[1]
            if np.max(np.abs(np.log(after / before))) < o.regional_tol:
                break
    starts, best = co.starts, co.best
    out = _full_graph(log, model, poses, seed, progress, marginals, o, max_sensor_degree, trace, stages, it1, t0)
    out.model.fit.update(start_options=W.options_json(start_options),
                         start_slopes=[[round(s.slope, 6), round(h, 1)] for s, h in zip(starts, co.held)
                                       if np.isfinite(s.slope)])
    out.notes.update({"hypothesis": list(starts[0].hypothesis), "start_log_evidence": starts[0].log_evidence,
                      "start_slope": starts[best].slope, "windows_placed": starts[best].windows_placed,
                      "start_model": starts[best].model, "start_poses": starts[best].poses})
    return out


def _full_graph(log: Log, model: Model, poses: np.ndarray, seed: int, progress: Progress, marginals: bool,
                o: CommandGraphOptions, max_sensor_degree: int, trace: list, stages: list, iterations: int,
                t0: float) -> Fit:
    """The fine graph's rounds from ``model`` and ``poses`` (T+1, 3), the sensor curve's degree raised when the
    readings demand (up to ``max_sensor_degree``), marginals: the end of every calibration."""
    full = layout(log, o.full_knot_dt)
    asked = len(model.reading_poly) - 1
    progress.stage("full graph", o.full_rounds)
    it2 = 0
    for attempt in range(2):
        model, kp, problem, st, its, converged = optimise_rounds(
            log, full, model, poses[full.knots], o.full_rounds, o.full_iterations, seed + 100, "full", trace, stages,
            progress, last_noise=False, settle=o.full_settle, noise_tol=o.noise_tol)
        it2 += its
        poses = fill_in(log, model, full.knots, kp)
        sel = problem.r_sel
        d = distances(poses[log.obs_step], log)[sel]
        better = None if attempt else choose_curve(d, log.obs_reading[sel], model.reading_poly, model.reading_sigma,
                                                   max_sensor_degree, model.reading_basis, o.sensor_curve)
        if better is None:
            break
        model = model.with_(reading_poly=better[0], reading_basis=better[1])     # the data demand another curve
        progress.stage(f"full graph, sensor degree {len(better[0]) - 1}"
                       + (" in 1/d" if better[1] == "inverse_distance" else ""), o.full_rounds)
    pose_std = np.full_like(poses, np.nan)
    if marginals:
        progress.stage("marginals", None)
        model, pose_std, _ = with_marginals(log, full, kp, problem, st, model)
    ll = problem_log_likelihood(problem, st, model)
    model = model.with_(distance_range=(float(d.min()), float(d.max())) if len(d) else (0.0, 0.0),
                        fit={"method": "graph", "iterations": iterations + it2,
                             "seconds": round(time.perf_counter() - t0, 3), "log_likelihood": ll,
                             "converged": converged, "knot_dt": o.full_knot_dt,
                             "outliers_set_aside": {"reading": int((~sel & ~np.isnan(log.obs_reading)).sum()),
                                                    "bearing": int((~problem.b_sel & ~np.isnan(log.obs_bearing)).sum())},
                             "sensor_degree": {"asked": asked, "fitted": len(model.reading_poly) - 1,
                                               "basis": model.reading_basis}})
    return Fit(model=model, poses=poses, pose_std=pose_std, cost=trace, stages=stages, iterations=iterations + it2,
               converged=converged, log_likelihood=ll, notes={"knots": full.knots})


def with_marginals(log: Log, lay: Layout, knot_poses: np.ndarray, problem: Problem, st: State, model: Model):
    """The model with the std of its command map and polynomial, the (T+1, 3) pose std (interpolated between
    knots) and each hooked effect's parameter std, from the marginals of ``problem`` at ``st``."""
    m, ridge = chain_marginals(problem, st)
    if ridge:
        warnings.warn(RIDGE_WARNING.format(ridge), RuntimeWarning, stacklevel=3)
    body = np.empty((lay.n_poses, 3))
    cov_xy = np.empty((lay.n_poses, 2, 2))
    for i in range(lay.n_poses):
        cov = m.marginalCovariance(X(i))
        body[i], cov_xy[i] = np.sqrt(np.diag(cov)), cov[:2, :2]
    knot_std = world_std(knot_poses, body, cov_xy)
    t = log.pose_times
    pose_std = np.column_stack([np.interp(t, t[lay.knots], knot_std[:, j]) for j in range(3)])
    std = np.sqrt(np.clip(np.diag(m.marginalCovariance(THETA)), 0, None))
    na, D = problem.n_action, problem.D
    model = model.with_(command=model.command.with_params(st.params, std[:na]), reading_poly_std=std[na:na + D])
    return model, pose_std, problem.effects_std(std)


# --------------------------------------------------------------------------- effects for continuous commands
EFFECTS = ("actuator_lag",)                       # catalog effects profiled (part of the command model) and diagnosed
NOISE_EFFECTS = (RMN.RegionalMotionNoise.name,)   # set by the noise step of every round, added on request only


def check_effects(effects, log: Log) -> None:
    """LogError unless every effect (name, class or instance) is one ``log`` can take: the profiled and noise
    effects of this module when the log measures the channels they need, or any least-squares effect whose
    own ``applicable`` accepts the log (fitted through its hooks, :func:`fit_hooked`)."""
    for e in effects:
        name = e if isinstance(e, str) else e.name
        base, member, _ = e.partition(":") if isinstance(e, str) else (name, "", "")
        if member and base in EFFECTS:
            raise LogError(f"--effect {e}: on continuous commands {base} is profiled in its own forms; "
                           f"give --effect {base}")
        if name in EFFECTS or name in NOISE_EFFECTS:
            continue
        inst = augmented.instantiate([e], log)[0]
        if inst.noise_only and inst.channel != "sensor":
            raise LogError(f"--effect {name}: a motion noise effect; of those continuous-command logs take "
                           f"{', '.join(NOISE_EFFECTS)}")
        why = inst.applicable(log)
        if why:
            raise LogError(f"--effect {name} cannot be fitted on {log.source or 'this log'}: {why}")


def hooked_effects(log: Log, model: Model, own=()) -> list:
    """Instances of ``model``'s effects that act through their hooks on ``log`` (all but the profiled and noise
    ones of this module); ``own``: user effect classes among them."""
    entries = {n: e for n, e in model.effects.items() if n not in EFFECTS and n not in NOISE_EFFECTS}
    return [cls(log) for cls in of_model(entries, own)]


def with_regional_noise(model: Model, log: Log, regions: RMN.Regions, fitted: Model) -> Model:
    """``model`` with regional_motion_noise on ``regions``, every region starting from ``fitted``'s
    forward and turn noise per median step (the turn variance shared half and half by k_t and k_d)."""
    v = np.abs(fitted.command.velocities(log.controls, log.dt)) * log.dt[:, None]
    r, turn = max(float(v[:, 0].mean()), 1e-6), max(float(v[:, 2].mean()), 1e-6)
    sf, _, st = np.asarray(fitted.motion_noise, float)
    k = np.tile([sf ** 2 / r, 0.5 * st ** 2 / turn, 0.5 * st ** 2 / r], (regions.count, 1))
    return model.with_(effects={**model.effects, RMN.RegionalMotionNoise.name: RMN.entry(regions, k)})


def with_effect(model: Model, name: str, value: float, order: int | None = None) -> Model:
    """``model`` with one profiled effect's parameter set (0 switches it off); ``order``: the lag's stages
    (default: the model's)."""
    if name not in EFFECTS:
        raise ValueError(f"{name!r} is not profiled on continuous-command logs ({', '.join(EFFECTS)} are)")
    order = int(order or model.command.lag_order) if value else 1
    entry = {"tau": float(value), **({"order": order} if order != 1 else {})}
    effects = {**{k: v for k, v in model.effects.items() if k != name}, **({name: entry} if value else {})}
    return model.with_(command=replace(model.command, lag=float(value), lag_order=order), effects=effects)


def effect_value(model: Model, name: str) -> float:
    """A profiled effect's value in ``model`` (the command model's lag)."""
    return model.command.lag


@dataclass
class Profile:
    """Profile log-likelihood of the coarse graph against one effect's parameter (noise at its maximum, outliers fixed)."""

    effect: str
    value: float                   # the maximum
    gain: float                    # log-likelihood at the maximum minus with the effect off (nats)
    n_data: int                    # residual rows, for BIC
    grid: list                     # (value, log-likelihood) pairs evaluated, in order
    order: int = 1                 # the lag's stages (ProfileOptions.lag_orders); one more free parameter when above 1

    @property
    def delta_bic(self) -> float:
        return float(-2 * self.gain + self.order * np.log(self.n_data))


def profile(log: Log, fit: Fit, name: str, effects=(), options: ProfileOptions | None = None,
            knot_dt: float = DEFAULTS.coarse_knot_dt) -> Profile:
    """Profile one continuous-log effect's parameter on the coarse graph of a fitted log (with the hooked ``effects``
    the model already has).

    Every evaluation sets the parameter, keeps ``fit``'s set-aside sightings, lets poses, command
    map and polynomial re-settle (LM from ``fit``'s own), moves each noise level to its
    maximum-likelihood value and re-settles once more; its value is the log-likelihood with the
    noise levels concentrated out, so two settings compare as a likelihood ratio on the same data.
    A grid brackets the maximum, Brent's bounded search refines it (``options``). An actuator lag supported with
    one stage (delta BIC below ``options.lag_order_support``) is profiled with two as well, and the order BIC
    prefers (one more parameter) is kept. ``knot_dt``: the coarse graph's knot spacing.
    """
    o = options or ProfileOptions()
    lay = layout(log, knot_dt)
    use = gate(log, fit.poses[log.obs_step], fit.model, effects=effects)
    start = fit.poses[lay.knots]
    n = residual_rows(log, lay, use)
    best = _profile_order(log, lay, use, start, fit.model, name, effects, n, 1, o)
    if name == "actuator_lag" and best.delta_bic < o.lag_order_support:
        for order in o.lag_orders[1:]:
            other = _profile_order(log, lay, use, start, fit.model, name, effects, n, order, o)
            if other.delta_bic < best.delta_bic:
                best = other
    return best


def _profile_order(log: Log, lay: Layout, use, start: np.ndarray, model: Model, name: str, effects, n: int,
                   order: int, o: ProfileOptions) -> Profile:
    """:func:`profile` for one lag order (1 for every other effect)."""
    seen: dict[float, float] = {}

    def value(x: float) -> float:
        x = round(float(x), 5)
        if x not in seen:
            seen[x] = settled_log_likelihood(log, lay, with_effect(model, name, x, order), use, start, effects,
                                             iterations=o.iterations)[0]
        return seen[x]

    grid = list(o.grid[name])
    lo_b, hi_b = o.bounds[name]
    vals = [value(x) for x in grid]
    i = int(np.argmax(vals))
    if i == len(grid) - 1:
        grid.append(hi_b)
        value(hi_b)
    elif i == 0 and grid[0] > lo_b:
        grid.insert(0, lo_b)
        value(lo_b)
        i += 1
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    if hi - lo > o.tol[name]:       # Brent's bounded search in the bracket (parabolic steps, golden fallback)
        minimize_scalar(lambda x: -value(x), bounds=(lo, hi), method="bounded", options={"xatol": o.tol[name] / 2})
    best = max(seen, key=seen.get)
    gain = float(seen[best] - value(0.0))
    return Profile(effect=name, value=float(best), gain=gain, n_data=n, grid=sorted(seen.items()), order=order)


def residual_rows(log: Log, lay: Layout, use) -> int:
    """Residual rows of a graph on ``lay`` with the sightings ``use`` keeps: the n of BIC."""
    return (3 * (lay.n_poses - 1) + int((use[0] & ~np.isnan(log.obs_reading)).sum())
            + int((use[1] & ~np.isnan(log.obs_bearing)).sum()))


def settled_log_likelihood(log: Log, lay: Layout, model: Model, use, start: np.ndarray, effects=(),
                           rounds: int = 1, tol: float = 1.0, iterations: int = ProfileOptions.iterations):
    """(log-likelihood with the noise levels concentrated out, model, the graph and its state) after settling
    ``model`` with ``effects`` on ``lay`` from knot poses ``start``: LM, every noise level to its maximum, LM again (sightings ``use``
    fixed), so two models compare as a likelihood ratio on the same data. With ``rounds`` > 1 the noise step and
    the second LM repeat until the log-likelihood moves by less than ``tol`` nats (an effect whose parameters move
    the poses far, as a latency does, needs them); ``iterations`` bounds the first LM (half as many after)."""
    problem = Problem(log, model, effects, lay=lay, gate=use, poses=start)
    st, _ = least_squares(problem, problem.state(start, model), max_iterations=iterations)
    model = problem.with_state(model, st)
    ll = -np.inf
    for _ in range(rounds):
        model = _ml_noise(problem, st, model)
        if problem.noise_effects:
            model = augmented.noise_effects(problem, st, model)[0]
            model = _ml_noise(Problem(log, model, effects, lay=lay, gate=use, poses=st.poses), st, model)
        problem = Problem(log, model, effects, lay=lay, gate=use, poses=st.poses)
        st, _ = least_squares(problem, st, max_iterations=iterations // 2)
        model = problem.with_state(model, st)
        last, ll = ll, _concentrated_log_likelihood(problem, st, model)
        if abs(ll - last) < tol:
            break
    return ll, model, problem, st


def _group_sums(problem: Problem, st: State) -> dict:
    r = problem.rows(st, jacobians=False)
    ae, re, be = r.action_e, r.reading_e, r.bearing_e
    sums = {"forward": ae[:, 0] ** 2, "lateral": ae[:, 1] ** 2, "turn": ae[:, 2] ** 2,
            "reading": re ** 2, "bearing": be ** 2}
    return {k: v for k, v in sums.items() if len(v)}     # a channel the log does not measure has no rows


def _ml_noise(problem: Problem, st: State, model: Model) -> Model:
    """Every noise level scaled to its maximum-likelihood value at ``st`` (whitened mean square 1)."""
    g = {k: float(np.sqrt(np.mean(v))) for k, v in _group_sums(problem, st).items()}
    m = problem.action.noise_rules.apply(np.asarray(model.motion_noise, float) * [g["forward"], g["lateral"], g["turn"]])
    return model.with_(motion_noise=m, reading_sigma=model.reading_sigma * g.get("reading", 1.0),
                       bearing_sigma=model.bearing_sigma * g.get("bearing", 1.0))


def _concentrated_log_likelihood(problem: Problem, st: State, model: Model) -> float:
    """log p(data | poses, model) with each noise group's scale at its maximum, up to a constant
    that does not depend on the poses or the command model: -n/2 log(sigma_ML^2) summed over groups. Under a
    false-detection mixture the sightings count by their mixture density instead, every one, gated or not (a
    concentrated Gaussian over the inlier-weighted rows would reward calling more of them false)."""
    base = {"forward": problem.motion_sigma[:, 0], "lateral": problem.motion_sigma[:, 1],
            "turn": problem.motion_sigma[:, 2]}
    out = 0.0
    if problem.mixed:
        out += mixture_log_likelihood(problem, st)
        out += float(np.sum(np.log(problem.r_scale[problem.r_idx])))       # the mixture's density has the scales in it
    for k, w2 in _group_sums(problem, st).items():
        if problem.mixed and k in ("reading", "bearing"):
            continue
        log_det = np.sum(np.log(base[k])) if k in base else len(w2) * np.log(getattr(problem, f"{k}_sigma"))
        out -= 0.5 * len(w2) * np.log(np.mean(w2)) + log_det
    return float(out - np.sum(np.log(problem.r_scale[problem.r_idx])))


def fit_hooked(log: Log, base: Fit, effects, seed: int = 0, progress: Progress | None = None,
               marginals: bool = True, options: CommandGraphOptions = DEFAULTS) -> Fit:
    """``base`` refitted with ``effects`` acting through their hooks (velocity, geometry, reading): their
    least-squares parameters join the command map in the fine graph, warm-started at their starts, for
    ``options.hooked_rounds`` rounds and then until the noise levels settle."""
    progress = progress or Progress()
    t0 = time.perf_counter()
    o = options
    effects = augmented.instantiate(effects, log)
    augmented.begin(effects, base.model, base.poses)
    full = layout(log, o.full_knot_dt)
    theta = augmented.theta_from_model(effects, base.model)     # the effects start where the model has them, else at
    model = base.model.with_(effects={**base.model.effects, **{   # their own starts
        e.name: e.describe(theta[s]) for e, s in zip(effects, augmented.parameter_slices(effects)) if not e.noise_only}})
    trace, stages = [], []
    progress.stage("effects", o.hooked_rounds)
    model, kp, problem, st, its, converged = optimise_rounds(
        log, full, model, base.poses[full.knots], o.hooked_rounds, o.full_iterations, seed + 300, "effects", trace,
        stages, progress, last_noise=False, settle=o.full_settle, effects=effects, noise_tol=o.noise_tol)
    poses = fill_in(log, model, full.knots, kp)
    pose_std, effect_std = np.full_like(poses, np.nan), {}
    if marginals:
        progress.stage("marginals", None)
        model, pose_std, effect_std = with_marginals(log, full, kp, problem, st, model)
    ll = problem_log_likelihood(problem, st, model)
    model = model.with_(fit={**base.model.fit, "iterations": base.iterations + its,
                             "seconds": round(base.model.fit.get("seconds", 0) + time.perf_counter() - t0, 3),
                             "log_likelihood": ll, "converged": converged, "effects_std": effect_std})
    return Fit(model=model, poses=poses, pose_std=pose_std, cost=base.cost + trace, stages=base.stages + stages,
               iterations=base.iterations + its, converged=converged, log_likelihood=ll,
               notes={**base.notes, "base_log_likelihood": base.log_likelihood,
                      "hooked_effects": [type(e) for e in effects]})


def curve_with_effects(log: Log, out: Fit, alt: Fit, hooked, warm: dict, seed: int, progress: Progress,
                       marginals: bool, options: CommandGraphOptions) -> Fit:
    """The sensor curve chosen again with the hooked effects fitted (when one acts on the sightings, else ``out``):
    ``out`` (``hooked`` fitted on the curve the fit without them chose) against them fitted on ``alt``, the curve it
    passed over. Without a false-detection mixture the wild readings' near-range misfit favours a steep 1/d curve
    that the mixture no longer needs (an independent floor: 0.023 m from the truth in 1/d, 0.010 m in d, 4,400 nats
    apart)."""
    effects = augmented.instantiate(hooked, log)
    if not any(e.channel == "sensor" for e in effects):
        return out
    other = fit_hooked(log, replace(alt, model=alt.model.with_(effects={**alt.model.effects, **warm})), hooked,
                       seed=seed, progress=progress, marginals=marginals, options=options)
    first, other = (out, other) if out.model.reading_basis == "distance" else (other, out)
    return better_curve(log, first, other, partial(sighting_log_likelihood, effects=effects), options.sensor_curve,
                        effects)


def fit_with_effects(log: Log, start: Model | None = None, effects=("actuator_lag",), seed: int = 0,
                     progress: Progress | None = None, marginals: bool = True,
                     regions: RMN.Regions | None = None, options: CommandGraphOptions = DEFAULTS,
                     base: Fit | None = None, max_sensor_degree: int = 0, free_basis: bool = False,
                     try_cross: bool = False) -> Fit:
    """``fit`` with effects (names, classes or instances): fit without them (or settle ``base``, a fit of ``start``
    by another method, on the full graph: the EM methods' effects start from their own fit), then for each profiled effect in
    turn profile it on the latest fit and refit with it set at its maximum. regional_motion_noise is not
    profiled: its regions (``regions``, default a 3 x 2 grid around the landmarks) start from the
    latest fit's noise levels and the noise step of every round of one more fit sets their k's. Every other
    effect acts through its hooks, its parameters fitted with the command map (:func:`fit_hooked`); when the
    model changes before they are added (a profiled lag, regional noise), they are fitted on the first fit too and
    start from there (from 0 a lens of k = -0.43 left MRCLAM robot 5's lag model where no damped step lowered the
    cost: the lens stayed at 0, the position error twice the warm start's). ``try_cross``: the fit without them
    chooses whether the turn map reads v (:func:`cross_choice`), and every later fit keeps its form."""
    progress = progress or Progress()
    start = start or start_model(log)
    check_effects(effects, log)
    named = [e if isinstance(e, str) else e.name for e in effects]
    profiled = [n for n in named if n in EFFECTS]
    noisy = [n for n in named if n in NOISE_EFFECTS]
    hooked = [e for e, n in zip(effects, named) if n not in EFFECTS and n not in NOISE_EFFECTS]
    curve = {"max_sensor_degree": max_sensor_degree, "free_basis": free_basis}   # chosen as the base's, in every fit
    alt = None               # the fit with the curve the latest one passed over, if it compared two
    if base is None:
        out, alt = fit_both_curves(log, start, seed=seed, progress=progress, marginals=marginals and not effects,
                                   options=options, try_cross=try_cross, **curve)
        if out.model.command.cross:  # the base's map form, in every later fit
            start = start.with_(command=start.command.with_cross())
    else:                    # settled on the full graph first: a profile reads the poses it starts from
        out = fit_hooked(log, base, [], seed=seed, progress=progress, marginals=False, options=options)
    chosen = out.model.fit.get("cross_term")
    warm = {}
    if hooked and (profiled or noisy):
        first = fit_hooked(log, out, hooked, seed=seed, progress=progress, marginals=False, options=options)
        warm = {e.name: first.model.effects[e.name] for e in augmented.instantiate(hooked, log) if not e.noise_only}
    profiles = []
    for i, name in enumerate(profiled):
        progress.stage(f"{name} profile", None)
        prof = profile(log, out, name, options=options.profile, knot_dt=options.coarse_knot_dt)
        profiles.append(prof)
        start = with_effect(start, name, prof.value, prof.order)
        out, alt = fit_both_curves(log, start, seed=seed, progress=progress,
                                   marginals=marginals and i == len(profiled) - 1 and not noisy and not hooked,
                                   options=options, **curve)
    if noisy:
        before = out.log_likelihood
        start = with_regional_noise(start, log, regions or RMN.Regions.around_landmarks(log), out.model)
        out, alt = fit_both_curves(log, start, seed=seed, progress=progress, marginals=marginals and not hooked,
                                   options=options, **curve)
        out.notes["regional_motion_noise"] = {"log_likelihood_gain": float(out.log_likelihood - before)}
    if hooked:
        out = fit_hooked(log, replace(out, model=out.model.with_(effects={**out.model.effects, **warm})), hooked,
                         seed=seed, progress=progress, marginals=marginals, options=options)
        if alt is not None:
            out = curve_with_effects(log, out, alt, hooked, warm, seed, progress, marginals, options)
    out.notes["profiles"] = profiles
    if chosen is not None:
        out.model.fit["cross_term"] = chosen
    return out
