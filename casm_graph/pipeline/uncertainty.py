"""``casm-graph uncertainty``: sample the noise levels, take the Laplace marginals of the rest, write UNC.

UNC gets posterior.json (INTERFACE section 5, plus the priors, the likelihood's cost and the
Laplace results), model.json (the input model at the posterior median noise levels, with the
table (or, for continuous commands, the command map) and polynomial at their posterior mean and
std, the Laplace marginals averaged over the noise posterior, the polynomial's covariance and the
sensor curve's 90 % band where the log measures readings), corner.png, trace.png and report.html.
Action-table logs use the segment-eliminated table likelihood, continuous-command logs (``v,w``,
either sensor channel or both) the command-map graph's (:mod:`casm_graph.analysis.likelihood`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from casm_graph.analysis import posterior as P
from casm_graph.analysis.likelihood import NoiseLikelihood, noise_likelihood
from casm_graph.fit import trajectory
from casm_graph.fit.calibration import Calibration, read_truth_model
from casm_graph.io.identifiability import check_identifiable
from casm_graph.io.log import Log, LogError, load
from casm_graph.io.output import atomic_dir, checked_out, json_text
from casm_graph.models.effects.regional_motion_noise import RegionalMotionNoise
from casm_graph.models.model import Model
from casm_graph.report import uncertainty as uncertainty_report

SCHEMA = "casm-graph/posterior/1"


@dataclass
class Uncertainty:
    """Everything the report and the tests read."""

    log: Log
    model: Model                # at the posterior median noise, with Laplace std
    ml: NoiseLikelihood
    chain: P.Chain
    intervals: dict              # each sampled quantity: median and ci90
    priors: dict
    cov_theta: np.ndarray        # table (or command map), polynomial and effect parameters, in the likelihood's order
    truth: dict | None
    seconds: float
    options: P.SamplerOptions = field(default_factory=P.SamplerOptions)

    def summary(self) -> str:
        """Each sampled noise level's median and 90 % interval, and the sampler's figures."""
        ch = self.chain
        lines = [f"posterior of {len(ch.names)} noise levels: {ch.walkers} walkers x {ch.steps} steps "
                 f"(burn-in {ch.burn_in}), acceptance {ch.acceptance:.2f}"]
        lines += [f"  {n:<24} {s['median']:.4g}  90% [{s['ci90'][0]:.4g}, {s['ci90'][1]:.4g}]"
                  for n, s in self.intervals.items()]
        if self.ml.set_aside():
            lines.append(f"  {self.ml.set_aside()} sighting(s) set aside as gross outliers")
        return "\n".join(lines + [f"  note: {n}" for n in ch.notes])

    def save(self, out, force: bool = False) -> Path:
        """Write UNC (posterior.json, model.json, corner.png, trace.png, report.html) all or nothing."""
        with atomic_dir(out, force=force, inputs=[self.log.source] if self.log.source else []) as tmp:
            (tmp / "posterior.json").write_text(json_text(self.to_json()))
            (tmp / "model.json").write_text(json_text(self.model.to_json()))
            uncertainty_report.write(tmp, self)
        return Path(out)

    def to_json(self) -> dict:
        ch = self.chain
        return {
            "schema": SCHEMA,
            "parameters": {n: {**s, "prior": self.priors[n].describe()} for n, s in self.intervals.items()},
            "sampler": {"options": self.options.to_json(), "walkers": ch.walkers, "steps": ch.steps,
                        "burn_in": ch.burn_in,
                        "acceptance_fraction": ch.acceptance,
                        "autocorr_time": {n: float(t) for n, t in zip(ch.names, ch.tau)},
                        "thin": ch.thin, "samples": int(len(ch.samples)), "too_short": ch.too_short,
                        "notes": ch.notes},
            "likelihood": {"method": "laplace",
                           "integrated_out": list(self.ml.integrated_out),
                           "linearisation": "MAP at the model's noise levels",
                           "sightings_set_aside": self.ml.set_aside(),
                           "evaluations": ch.evaluations,
                           "seconds_per_evaluation": ch.seconds_per_evaluation,
                           "cpu_seconds_per_evaluation": ch.cpu_seconds_per_evaluation,
                           "steps": int(self.log.steps)},
            "laplace": self._laplace_json(),
            "seconds": round(self.seconds, 2),
        }

    def _laplace_json(self) -> dict:
        """The Laplace std of the table or command map, and of the sensor curve where the log measures readings."""
        m = self.model
        out = {"noise_draws": self.options.draws, **m.action.std_json()}
        if m.has("reading"):
            out.update(reading_poly_std=m.reading_poly_std.tolist(), reading_band=m.reading_band())
        return out


def prepare(log: Log, model: Model, poses: np.ndarray | None = None,
            source: str = "the model") -> tuple[Model, np.ndarray]:
    """The model ready for ``log`` and a start trajectory (T+1, 3).

    ``poses`` when given; else, for an action table, the EKF smoother's (the model indexed like the
    log's actions), for continuous commands a fresh :func:`casm_graph.fit.continuous.fit` of the log.
    """
    model = model.for_log(log, source)
    if RegionalMotionNoise.name in model.effects:
        raise LogError(f"{source}: uncertainty samples one forward and one turn noise level, not "
                       f"{RegionalMotionNoise.name}'s per-region ones; calibrate without that effect")
    return model, (trajectory.smoothed(log, model) if poses is None else poses)


def mixed_marginals(ml: NoiseLikelihood, samples: np.ndarray, draws: int = P.SamplerOptions.draws, seed: int = 0):
    """Mean shift from the MAP and covariance of the integrated-out parameters, noise integrated out.

    The Laplace posterior of the parameters given the noise, N(MAP + shift(lambda), S(lambda)^-1),
    is averaged over ``draws`` posterior samples of the noise (law of total variance), so a noise
    level the log cannot pin down widens the table's (or command map's) intervals as much as its
    posterior says.
    """
    rng = np.random.default_rng(seed)
    pick = samples[rng.choice(len(samples), size=min(draws, len(samples)), replace=False)]
    shifts, covs = [], []
    for x in pick:
        shift, C = ml.parameter_moments(x)
        covs.append(C)
        shifts.append(shift)
    shifts = np.array(shifts)
    cov = np.mean(covs, axis=0) + (np.cov(shifts.T) if len(shifts) > 1 else 0.0)
    return shifts.mean(axis=0), cov


def posterior_model(model: Model, ml: NoiseLikelihood, x_med: np.ndarray, shift: np.ndarray, cov: np.ndarray) -> Model:
    """``model`` at noise levels ``x_med``, its action model, polynomial and effects at their posterior mean with
    their std (the polynomial's only where the log measures readings). The parameter vector is the graph's:
    the action part's parameters, the polynomial, the least-squares effect parameters."""
    pb, st = ml.problem, ml.state
    na, D = pb.n_action, pb.D
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    sr, sb, mot, theta = ml._split(x_med)
    theta = theta.copy()
    theta[pb.ls_index] += shift[na + D:]
    effects = {**model.effects, **{e.name: e.describe(theta[s]) for e, s in zip(pb.effects, pb.slices)}}
    kw = {}
    if model.has("reading"):
        d = ml.reading_distances()
        kw = dict(reading_poly=st.poly + shift[na:na + D], reading_poly_std=sd[na:na + D],
                  reading_poly_cov=cov[na:na + D, na:na + D],
                  distance_range=(float(d.min()), float(d.max())) if len(d) else model.distance_range)
    effects_std = {**model.fit.get("effects_std", {}), **pb.effects_std(sd)}
    new = pb.action.with_params(model, np.ravel(st.action) + shift[:na], sd[:na])
    return new.with_(reading_sigma=sr, bearing_sigma=sb, motion_noise=mot, effects=effects, **kw,
                     fit={**model.fit, **({"effects_std": effects_std} if effects_std else {}),
                          "uncertainty": "noise levels: posterior median; action model, effects and polynomial: "
                                         "Laplace marginals averaged over the noise posterior"})


def compute(log: Log, model: Model, poses: np.ndarray, priors: tuple[str, ...] = (),
            options: P.SamplerOptions | None = None, seed: int = 0, truth: dict | None = None, progress=None,
            pool=None) -> Uncertainty:
    """Sample the noise levels of ``model`` on ``log`` and the Laplace marginals at their posterior median
    (``pool``: anything with ``map``, e.g. a Dask cluster's, to evaluate emcee's walkers on).

    An action-table model takes the table likelihood, a command map (continuous commands) the
    continuous one; ``poses`` (T+1, 3) is the start the MAP is found from."""
    t0 = time.perf_counter()
    overrides = dict(P.parse_prior(s) for s in priors)
    if progress is not None:
        progress.stage("MAP", None)
    # small dense blocks only: BLAS threads would spin and triple the cost of every evaluation
    with threadpool_limits(1):
        ml = noise_likelihood(log, model, poses)
        pri = P.priors_for(ml, overrides)
        o = options or P.SamplerOptions()
        ch = P.run(ml, pri, o, seed=seed, progress=progress, pool=pool)
        summ = P.summary(ch)
        if progress is not None:
            progress.stage("marginals", None)
        x_med = np.array([summ[n]["median"] for n in ml.names])
        shift, cov = mixed_marginals(ml, ch.samples, draws=o.draws, seed=seed)
    new = posterior_model(model, ml, x_med, shift, cov)
    return Uncertainty(log, new, ml, ch, summ, pri, cov, truth, time.perf_counter() - t0, o)


def uncertainty(log: Log, calibration: Calibration | Model, priors: tuple[str, ...] = (), walkers: int | None = None,
                max_steps: int | None = None, seed: int = 0, progress=None, pool=None,
                options: P.SamplerOptions | None = None) -> Uncertainty:
    """The posterior of the noise levels (emcee) and the Laplace marginals of the rest; in memory (``save`` writes UNC).
    ``walkers`` and ``max_steps``, when given, replace those of ``options``."""
    check_identifiable(log)
    for s in priors:
        P.parse_prior(s)
    if isinstance(calibration, Calibration):
        if isinstance(calibration.model, dict):
            raise LogError(f"uncertainty: the {calibration.options.method} models of a 1-D log have no posterior here")
        model = calibration.model
        poses = np.column_stack([calibration.trajectory[k] for k in ("x", "y", "theta")])
    else:
        model, poses = calibration, None
    model, poses = prepare(log, model, poses)
    return compute(log, model, poses, priors, sampler_options(options, walkers, max_steps), seed,
                   read_truth_model(log.source), progress, pool=pool)


def sampler_options(options: P.SamplerOptions | None, walkers: int | None, max_steps: int | None) -> P.SamplerOptions:
    """``options`` (the defaults when None) with ``walkers`` and ``max_steps`` put in where given."""
    o = options or P.SamplerOptions()
    given = {k: v for k, v in (("walkers", walkers), ("max_steps", max_steps)) if v is not None}
    return replace(o, **given)


def run(log_dir, model_path, out, priors: tuple[str, ...] = (), walkers: int | None = None, max_steps: int | None = None,
        seed: int = 0, progress=None, force: bool = False, pool=None) -> Uncertainty:
    """The command: check everything first (bad input writes nothing), compute, write UNC all or nothing."""
    checked_out(out, force, inputs=[log_dir, model_path])
    model_path = Path(model_path)
    for s in priors:
        P.parse_prior(s)
    model = Model.load(model_path)
    log = load(log_dir)
    model, poses = prepare(log, model, trajectory.from_run(log, model_path), model_path.name)
    unc = compute(log, model, poses, priors, sampler_options(None, walkers, max_steps), seed,
                  read_truth_model(log.source), progress, pool=pool)
    if progress is not None:
        progress.stage("report", None)
    unc.save(out, force=force)
    return unc
