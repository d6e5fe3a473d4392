"""Effects in a log's graph: their parameters, priors and hooks as the graph uses them, the noise step and marginals.

The velocity table, the sensor polynomial and the least-squares parameters of every effect travel
together as one vector variable of :class:`casm_graph.graph.problem.Problem` (an action step may
touch two table rows and an effect). The effect factors of :mod:`factors.effect_motion` and
:mod:`factors.effect_sighting` give residuals and Jacobians, exact (tests/test_effects.py) except
that the velocity a latency shift uses is differentiated through the table row alone, not through
other motion effects.
"""
from __future__ import annotations

import copy
import itertools

import numpy as np

import factors
from casm_graph.graph import chain
from casm_graph.graph import noise as noisemod
from casm_graph.io.log import Log, LogError, wrap
from casm_graph.models.effects import Effect
from casm_graph.models.effects import get as get_effect
from casm_graph.models.model import Model

EFFECT_PRIOR_SCALE = 1e4          # weak prior (in units of each parameter's scale) where an effect has none
UNDETERMINED = ("the log does not determine the noise levels (the graph's information is singular, or a channel's "
                "residuals vanish): is a landmark far from the others, or are there too few sightings?")


def instantiate(names_or_effects, log: Log) -> list[Effect]:
    """Effect instances for ``log`` from names, classes or instances."""
    out = []
    for e in names_or_effects:
        if isinstance(e, str):
            e = get_effect(e)
        out.append(e(log) if isinstance(e, type) else e)
    return out


def at_prior_widths(names_or_effects, log: Log) -> list[list[Effect]]:
    """Effect instances for ``log``, one list per combination of the ``prior_widths`` of the classes that offer a
    choice (a single list when none does)."""
    first = instantiate(names_or_effects, log)
    out = []
    for widths in itertools.product(*(e.prior_widths if len(e.prior_widths) > 1 else (e.prior_width,) for e in first)):
        effects = [copy.copy(e) for e in first]
        for e, w in zip(effects, widths):
            e.prior_width = w
        out.append(effects)
    return out


def begin(effects: list[Effect], model: Model, poses: np.ndarray) -> None:
    """Each least-squares effect ``model`` does not hold yet takes its start from ``poses`` (T+1, 3), a fit of
    ``model`` without it (:meth:`Effect.begin`)."""
    for e in effects:
        if not e.noise_only and not model.effects.get(e.name):
            e.begin(model, poses)


def theta_from_model(effects: list[Effect], model: Model) -> np.ndarray:
    """Effect parameters stored in ``model.effects``, or each effect's start where absent (what else an entry
    records, each effect takes back through ``restore``)."""
    return np.array([v for e in effects for v in e.theta_of(model.effects.get(e.name, {}))], float)


def reading_scale(effect_slices, theta: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Each reading's sigma factor: the product of the effects' ``reading_scale`` at ``distance`` (``effect_slices``:
    (effect, its slice of ``theta``) pairs; 1 everywhere without a noise effect)."""
    scale = np.ones(len(distance))
    for e, s in effect_slices:
        scale = scale * e.reading_scale(theta[s], distance, {})
    return scale


def parameter_slices(effects: list[Effect]) -> list[slice]:
    """Each effect's slice of the stacked parameter vector theta, in the effects' order."""
    cuts = np.concatenate([[0], np.cumsum([len(e.params) for e in effects])]).astype(int)
    return [slice(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:])]


def parameter_prior(effects: list[Effect], slices: list[slice]) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sigma) of the prior on the least-squares effect parameters: each effect's own (at its
    ``prior_width``), else weak around 0."""
    pm, ps = [np.zeros(0)], [np.zeros(0)]
    for e, s in zip(effects, slices):
        if e.noise_only:
            continue
        pr = e.prior()
        if pr is None:
            pm.append(np.zeros(s.stop - s.start))
            ps.append(EFFECT_PRIOR_SCALE * np.maximum(np.asarray(e.scale, float), 1e-6))
        else:
            pm.append(np.asarray(pr[0], float))
            ps.append(np.asarray(pr[1], float) * e.prior_width)
    return np.concatenate(pm), np.concatenate(ps)


def motion_function(motion_effects, ctx: dict, theta: np.ndarray):
    """The velocity a step runs under ``motion_effects`` ((effect, slice) pairs) as a function of the
    action model's velocity ``v``, the previous one, the pose and (optionally) the parameters."""

    def bound(v, v_prev, pose, th=None):
        c = {**ctx, "v_prev": v_prev, "pose": pose}
        th = theta if th is None else th
        for e, s in motion_effects:
            v = e.velocity(th[s], v, c)
        return v

    return bound


def sensor_function(sensor_effects, ctx: dict, landmark_xy: np.ndarray, basis: str = "distance"):
    """Predicted reading, bearing and distance of observations ``idx`` under ``sensor_effects`` ((effect,
    slice) pairs), as a function of the parameters, the poses and the sensor curve's coefficients (in
    ``basis``, :mod:`factors.reading`); ``landmark_xy`` per observation."""

    def fn(theta, pose, poly, idx, velocity=None):
        c = {k: (v[idx] if isinstance(v, np.ndarray) else v) for k, v in ctx.items()}
        c["pose"] = pose
        if velocity is not None:
            c["velocity"] = velocity[idx]
        p, lm = pose, landmark_xy[idx]
        for e, s in sensor_effects:
            p, lm = e.geometry(theta[s], p, lm, c)
        rel = lm - p[:, :2]
        d = np.hypot(rel[:, 0], rel[:, 1])
        bearing = np.arctan2(rel[:, 1], rel[:, 0]) - p[:, 2]
        c.update(distance=d, bearing=wrap(bearing), image_angle=wrap(bearing - c["pan"]))
        pred = factors.reading.curve(d, poly, basis)
        for e, s in sensor_effects:
            pred = e.reading(theta[s], pred, c)
        return pred, bearing, d

    return fn


def estimate_noise(problem, st, model: Model, seed: int = 0, relax: float = 1.0,
                   poses_only: bool = False) -> tuple[Model, np.ndarray]:
    """Every noise level of ``problem`` (a :class:`casm_graph.graph.problem.Problem`) re-estimated at its optimum
    ``st`` (:mod:`casm_graph.graph.noise`), and the noise-only effect parameters (also described in the model's
    effects); the one noise step of every graph. The action part says what the motion levels may be
    (``noise_rules``) and re-estimates a motion-noise effect it places (``motion_noise_step``).
    ``poses_only``: the parameters were held, so their columns take no degrees of freedom.

    ``relax`` > 1 over-relaxes the fixed-point step (in log sigma), which otherwise creeps down slowly from
    a loose start because the trajectory follows whatever freedom it is given. The hat traces' solves are
    :func:`casm_graph.graph.noise.information_solver`'s; a log they cannot answer (a landmark hundreds of
    kilometres off) ends in one line.
    """
    A, e, groups = problem.jacobian(st, poses_only=poses_only)
    lu = noisemod.information_solver(A, problem.lay.n_poses)
    if lu is None:
        raise LogError(UNDETERMINED)
    traces = noisemod.hat_traces(A, groups, seed=seed, lu=lu)
    rules = problem.action.noise_rules
    robust_groups = ("reading", "bearing") if np.isfinite(problem.k) and rules.huber_efficiency else ()
    new = {k: v ** relax for k, v in noisemod.group_scales(e, groups, traces, counts=problem.counts,
                                                            huber=robust_groups).items()}
    if not all(np.isfinite(v) and v > 0 for v in new.values()):
        raise LogError(UNDETERMINED)
    motion = rules.apply(np.asarray(model.motion_noise, float) * [new["forward"], new["lateral"], new["turn"]])
    m = model.with_(motion_noise=motion, reading_sigma=model.reading_sigma * new["reading"],
                    bearing_sigma=model.bearing_sigma * new["bearing"])
    return noise_effects(problem, st, problem.action.motion_noise_step(m, problem, e, A, groups, lu))


def noise_effects(problem, st, model: Model) -> tuple[Model, np.ndarray]:
    """``model`` and ``st``'s effect parameters with the noise-only sensor effects' re-estimated by their own
    ``estimate_noise`` from the residuals at ``st`` (inlier weights those the least squares ran with) under
    ``model``'s sigmas."""
    m, theta = model, st.theta.copy()
    if not problem.noise_effects:
        return m, theta
    t = problem.observation_terms(st)
    for eff, s in problem.noise_effects:
        # a mixture's share counts every sighting not held out, the gated ones too; a noise law the readings in
        # the graph
        k = problem.obs_mask & problem.measured if eff.mixture else problem.r_sel
        z_r = t["reading"][k] / (m.reading_sigma * t["scale"][k])
        z_b = t["bearing"][k] / m.bearing_sigma
        ctx = {"weight": t["weight"][k], "reading_scale": t["scale"][k], "reading_sigma": m.reading_sigma,
               "bearing_sigma": m.bearing_sigma}
        theta[s] = eff.estimate_noise(theta[s], z_r, z_b, t["distance"][k], ctx)
    # the reading sigma follows its new scales: the estimate under the old ones, times the change of the readings'
    # mean square under the new (a growth estimated with the sigma profiled out, left beside a sigma estimated
    # under the old growth, made a pair worse than either: an independent world's growth of 0.71 per metre lost
    # 185 nats in two rounds and was never named)
    k = problem.r_sel & (t["weight"] > 0.5)
    if k.any():
        e = t["reading"][k]
        new = reading_scale(problem.sensor_effects, theta, t["distance"][k])
        before, after = np.mean((e / t["scale"][k]) ** 2), np.mean((e / new) ** 2)
        if before > 0 and after > 0 and np.isfinite(after):
            m = m.with_(reading_sigma=m.reading_sigma * float(np.sqrt(after / before)))
    described = {eff.name: eff.describe(theta[s]) for eff, s in problem.noise_effects}
    return m.with_(effects={**m.effects, **described}), theta


def marginals(problem, st) -> tuple[np.ndarray, np.ndarray]:
    """Pose covariances (K, 3, 3) and the parameter covariance (n_theta, n_theta) at ``st``.

    The parameter block is the inverse Schur complement of the pose chain (the exact marginal of
    the Gaussian approximation); each pose's covariance adds the parameters' share to its
    conditional covariance from the chain.
    """
    D, B, F, gp, Htt, gt = problem.normal_equations(st)
    n = F.shape[2]
    Xs = chain._chain_solve(D, B, np.ascontiguousarray(F), 0.0)           # Hpp^-1 F
    Ff, Xf = F.reshape(-1, n), Xs.reshape(-1, n)
    cov_t = np.linalg.inv(Htt - Ff.T @ Xf)
    cond, _, _ = chain.select_inverse(D, B)
    cov_p = cond + np.einsum("kin,nm,kjm->kij", Xs, cov_t, Xs)
    return cov_p, cov_t
