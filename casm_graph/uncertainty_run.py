"""``casm-graph uncertainty``: sample the noise levels, take the Laplace marginals of the rest, write UNC.

UNC gets posterior.json (INTERFACE section 5, plus the priors, the likelihood's cost and the
Laplace results), model.json (the input model at the posterior median noise levels, with the
table and polynomial at their posterior mean and std, the Laplace marginals averaged over the
noise posterior, the polynomial's covariance and the sensor curve's 90 % band), corner.png,
trace.png and report.html.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from . import posterior as P
from .calibrate import read_truth_model
from .diagnose_run import check_compatible, start_trajectory
from .log import Log, LogError, load
from .model import Model
from .uncertainty import MarginalLikelihood, likelihood

SCHEMA = "casm-graph/posterior/1"
DRAWS = 64                 # posterior noise draws the table's and polynomial's Laplace marginals are averaged over


@dataclass
class Uncertainty:
    """Everything the report and the tests read."""

    log: Log
    model: Model                # at the posterior median noise, with Laplace std
    ml: MarginalLikelihood
    chain: P.Chain
    summary: dict
    priors: dict
    cov_theta: np.ndarray
    truth: dict | None
    seconds: float
    draws: int = DRAWS

    def to_json(self) -> dict:
        ch = self.chain
        return {
            "schema": SCHEMA,
            "parameters": {n: {**s, "prior": self.priors[n].describe()} for n, s in self.summary.items()},
            "sampler": {"walkers": ch.walkers, "steps": ch.steps, "burn_in": ch.burn_in,
                        "acceptance_fraction": ch.acceptance,
                        "autocorr_time": {n: float(t) for n, t in zip(ch.names, ch.tau)},
                        "thin": ch.thin, "samples": int(len(ch.samples)), "too_short": ch.too_short,
                        "notes": ch.notes},
            "likelihood": {"method": "laplace",
                           "integrated_out": ["poses", "velocity table", "sensor polynomial",
                                              "effect parameters (least squares)"],
                           "linearisation": "MAP at the model's noise levels",
                           "evaluations": ch.evaluations,
                           "seconds_per_evaluation": ch.seconds_per_evaluation,
                           "cpu_seconds_per_evaluation": ch.cpu_seconds_per_evaluation,
                           "steps": int(self.log.steps)},
            "laplace": {"noise_draws": self.draws,
                        "velocity_std": {str(int(a)): s.tolist() for a, s in
                                         zip(self.model.action_ids, self.model.velocity_std)},
                        "reading_poly_std": self.model.reading_poly_std.tolist(),
                        "reading_band": self.model.reading_band()},
            "seconds": round(self.seconds, 2),
        }


def prepare(log: Log, model: Model, model_path: Path) -> tuple[Model, np.ndarray]:
    """The model indexed like the log's actions, and a start trajectory (RUN/trajectory.csv when it fits)."""
    if model.command is not None or log.action is None:
        raise LogError(f"{model_path.name}: uncertainty needs a table action model and a log with an 'action' column")
    check_compatible(log, model, model_path.name)
    model = model.with_(velocities=model.velocities[np.searchsorted(model.action_ids, log.action_ids)],
                        action_ids=log.action_ids, velocity_std=None)
    return model, start_trajectory(log, model, model_path)


def mixed_marginals(ml: MarginalLikelihood, samples: np.ndarray, draws: int = DRAWS, seed: int = 0):
    """Mean shift from the MAP and covariance of table, polynomial and effect parameters, noise integrated out.

    The Laplace posterior of the parameters given the noise, N(MAP + shift(lambda), S(lambda)^-1),
    is averaged over ``draws`` posterior samples of the noise (law of total variance), so a noise
    level the log cannot pin down widens the table's intervals as much as its posterior says.
    """
    rng = np.random.default_rng(seed)
    pick = samples[rng.choice(len(samples), size=min(draws, len(samples)), replace=False)]
    shifts, covs = [], []
    for x in pick:
        _, _, _, S, gt = ml.reduce(x)
        C = np.linalg.inv(S)
        covs.append(C)
        shifts.append(-C @ gt)
    shifts = np.array(shifts)
    cov = np.mean(covs, axis=0) + (np.cov(shifts.T) if len(shifts) > 1 else 0.0)
    return shifts.mean(axis=0), cov


def compute(log: Log, model: Model, poses: np.ndarray, priors: tuple[str, ...] = (), walkers: int | None = None,
            max_steps: int = 5000, seed: int = 0, truth: dict | None = None, progress=None,
            draws: int = DRAWS) -> Uncertainty:
    """Sample the noise levels of ``model`` on ``log`` and the Laplace marginals at their posterior median."""
    t0 = time.perf_counter()
    overrides = dict(P.parse_prior(s) for s in priors)
    if progress is not None:
        progress.stage("MAP", None)
    # small dense blocks only: BLAS threads would spin and triple the cost of every evaluation
    with threadpool_limits(1):
        ml = likelihood(log, model, poses)
        pri = P.priors_for(ml, overrides)
        ch = P.run(ml, pri, walkers=walkers, max_steps=max_steps, seed=seed, progress=progress)
        summ = P.summary(ch)
        if progress is not None:
            progress.stage("marginals", None)
        x_med = np.array([summ[n]["median"] for n in ml.names])
        shift, cov = mixed_marginals(ml, ch.samples, draws=draws, seed=seed)
    pb, st = ml.problem, ml.state
    A, D = pb.A, pb.D
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    sr, sb, mot, th = ml._split(x_med)
    effects = dict(model.effects)
    th = th.copy()
    th[pb.ls_index] += shift[3 * A + D:]
    for e, s in zip(pb.effects, pb.slices):
        effects[e.name] = e.describe(th[s])
    d = pb.predictions(st)["distance"][np.isfinite(log.obs_reading)]
    new = model.with_(velocities=st.velocities + shift[:3 * A].reshape(-1, 3), velocity_std=sd[:3 * A].reshape(-1, 3),
                      reading_poly=st.poly + shift[3 * A:3 * A + D], reading_poly_std=sd[3 * A:3 * A + D],
                      reading_poly_cov=cov[3 * A:3 * A + D, 3 * A:3 * A + D], reading_sigma=sr, bearing_sigma=sb,
                      motion_noise=mot, effects=effects,
                      distance_range=(float(d.min()), float(d.max())) if len(d) else model.distance_range,
                      fit={**model.fit, "uncertainty": "noise levels: posterior median; table and polynomial: "
                                                       "Laplace marginals averaged over the noise posterior"})
    return Uncertainty(log, new, ml, ch, summ, pri, cov, truth, time.perf_counter() - t0, draws)


def run(log_dir, model_path, out, priors: tuple[str, ...] = (), walkers: int | None = None, max_steps: int = 5000,
        seed: int = 0, progress=None) -> Uncertainty:
    """The command: load and check everything first (bad input writes nothing), compute, write UNC."""
    model_path = Path(model_path)
    for s in priors:
        P.parse_prior(s)
    model = Model.load(model_path)
    log = load(log_dir)
    model, poses = prepare(log, model, model_path)
    unc = compute(log, model, poses, priors, walkers, max_steps, seed, read_truth_model(Path(log_dir)), progress)
    if progress is not None:
        progress.stage("report", None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "posterior.json").write_text(json.dumps(unc.to_json(), indent=2))
    unc.model.save(out / "model.json")
    from . import uncertainty_report
    uncertainty_report.write(out, unc)
    return unc
