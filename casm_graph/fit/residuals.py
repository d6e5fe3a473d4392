"""Residuals of a fitted model on its log, per channel, as plain arrays, with their covariates.

Channels follow INTERFACE section 4: ``forward``, ``lateral``, ``turn`` (motion residuals in the
body frame of each segment's start pose, per step of the segment) and ``reading``, ``bearing``.
:func:`channels` gives them whitened (measured minus predicted over the noise sigma) with every
covariate of INTERFACE section 4 attached, from the effect graph of :mod:`casm_graph.graph.augmented`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from casm_graph.graph import augmented, chain
from casm_graph.graph.actions.base import sighting_means, velocity_window
from casm_graph.graph.actions.command_poly import COMMAND_CHANGE
from casm_graph.graph.problem import Problem, State
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects.regional_motion_noise import region_of
from casm_graph.models.effects.surface_friction import NODES, extent_around
from casm_graph.models.model import Model

LJUNG_BOX_LAGS = 20


def step_motion(poses: np.ndarray, log: Log, model: Model) -> np.ndarray:
    """(T, 3) measured minus predicted displacement of every step (``poses`` (T+1, 3)) under the action model's
    steps, start body frame: any kind of action model, its effects left out."""
    a, b = poses[:-1], poses[1:]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    meas = np.column_stack([c * ex + s * ey, -s * ex + c * ey, b[:, 2] - a[:, 2]])
    r = meas - model.step_displacements(log)
    r[:, 2] = wrap(r[:, 2])
    return r


def sighting_residuals(log: Log, poses_at_obs: np.ndarray, model: Model, effects=()) -> dict:
    """Per sighting: distance and bearing from its pose, and the reading and bearing residuals
    (measured minus predicted, in the sensor's units; NaN where not measured), through the sensor
    hooks of ``effects`` (their parameters from ``model.effects``) when there are any."""
    rel = log.landmark_xy[log.landmark_index] - poses_at_obs[:, :2]
    d = np.hypot(rel[:, 0], rel[:, 1])
    bearing = wrap(np.arctan2(rel[:, 1], rel[:, 0]) - poses_at_obs[:, 2])
    sensor = [(e, s) for e, s in zip(effects, augmented.parameter_slices(list(effects))) if e.channel == "sensor"]
    if sensor:
        ctx = {"t": log.obs_t - log.pose_times[0], "landmark": log.landmark_index, "pan": log.camera_pan,
               "velocity": sighting_means(log, model.step_velocities(log), velocity_window(model, effects))}
        fn = augmented.sensor_function(sensor, ctx, log.landmark_xy[log.landmark_index], model.reading_basis)
        pred, b, _ = fn(augmented.theta_from_model(list(effects), model), poses_at_obs,
                        np.asarray(model.reading_poly, float), np.arange(len(log.obs_t)))
        return {"distance": d, "bearing": bearing, "reading": log.obs_reading - pred,
                "bearing_residual": wrap(log.obs_bearing - b)}
    return {"distance": d, "bearing": bearing, "reading": log.obs_reading - model.reading(d),
            "bearing_residual": wrap(log.obs_bearing - bearing)}


def observation(poses_at_obs: np.ndarray, log: Log, model: Model, effects=()) -> tuple[np.ndarray, np.ndarray]:
    """Reading and bearing residuals (measured minus predicted; NaN where not measured): from :func:`sighting_residuals`."""
    res = sighting_residuals(log, poses_at_obs, model, effects)
    return res["reading"], res["bearing_residual"]


def distances(poses_at_obs: np.ndarray, log: Log) -> np.ndarray:
    """Distance from each observation's pose to its landmark."""
    rel = log.landmark_xy[log.landmark_index] - poses_at_obs[:, :2]
    return np.hypot(rel[:, 0], rel[:, 1])


def ljung_box(r: np.ndarray, lags: int = LJUNG_BOX_LAGS) -> float:
    """p-value of the Ljung-Box test that the series ``r`` is white."""
    r = np.asarray(r, float) - np.mean(r)
    n = len(r)
    if n <= lags + 1:
        return float("nan")
    den = np.sum(r * r)
    rho = np.array([np.sum(r[k:] * r[:-k]) / den for k in range(1, lags + 1)])
    q = n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, lags + 1)))
    return float(stats.chi2.sf(q, lags))


MOTION_COVARIATES = ("time", "x", "y", "place", "heading", "speed", "turn_rate", "time_since_action_change", "action")
SENSOR_COVARIATES = ("time", "x", "y", "heading", "speed", "turn_rate", "distance", "bearing",
                     "image_angle", "landmark")
CATEGORICAL = ("action", "landmark", "place")


def place(xy: np.ndarray) -> np.ndarray:
    """Where on the floor each (x, y) is: the cell of a grid over the visited area (the friction field's grid),
    a categorical covariate that finds a patch a split along x or y alone dilutes."""
    x0, y0, x1, y1 = extent_around(xy)
    return region_of(xy[:, :2] - [x0, y0], (x1 - x0, y1 - y0), (NODES, NODES)).astype(float)


@dataclass
class Channel:
    name: str
    residual: np.ndarray          # whitened, measured minus predicted
    raw: np.ndarray               # same in the channel's own unit (m, rad, px)
    time: np.ndarray              # s since the log began (orders the series for whiteness)
    covariates: dict              # name -> (n,) array; NaN where unknown
    command: np.ndarray | None = field(default=None, repr=False)   # motion: the model's velocity on this axis
    span: np.ndarray | None = field(default=None, repr=False)      # motion: s each residual covers
    leverage: np.ndarray | None = field(default=None, repr=False)  # sightings: the share of each one's noise the
    #                                                                smoothed pose absorbs (:func:`sighting_leverage`)


def sighting_leverage(problem: Problem, st: State, rows=None) -> dict[str, np.ndarray]:
    """Per observation, the leverage h = j Sigma j^T of its reading and of its bearing row (whitened pose Jacobian
    j, the smoothed pose's covariance Sigma with the parameters held; NaN where not measured). A residual's
    variance is its noise's times 1 - h: a sighting that pins its pose (near, where the sensor curve is steep)
    leaves a smaller residual, which a test of the residuals' spread would read as noise growing with distance.
    ``rows``: the problem's rows at ``st`` with their pose Jacobians, when the caller has them."""
    r = problem.rows(st, parameters=False) if rows is None else rows
    D, B = chain.information_blocks(problem, st, rows=r)
    try:
        cov = chain.select_inverse(D, B)[0]
    except np.linalg.LinAlgError:
        return {}
    out = {}
    for name, J, idx in (("reading", r.reading_J[0], problem.r_idx), ("bearing", r.bearing_J, problem.b_idx)):
        h = np.full(len(problem.log.obs_t), np.nan)
        h[idx] = np.einsum("ni,nij,nj->n", J, cov[problem.obs_knot[idx]], J)
        out[name] = h
    return out


def channels(problem: Problem, st: State, command_change: float = COMMAND_CHANGE) -> dict[str, Channel]:
    """Residual channels of ``st`` under ``problem`` (its noise levels, effects, masks and gate), any action model:
    the motion channels' own covariates come from the action part (``command_change``: a continuous log's
    jump that counts as a new action)."""
    log = problem.log
    out = {}
    r = problem.rows(st, parameters=False)      # the pose Jacobians serve the leverage below
    P = st.poses[:-1]
    t, own, commanded, span = problem.action.motion_covariates(st.poses, st.action, st.theta, command_change)
    cov = {"time": t, "x": P[:, 0], "y": P[:, 1], "place": place(P), "heading": P[:, 2], **own}
    for k, name in enumerate(("forward", "lateral", "turn")):
        out[name] = Channel(name, r.action_e[:, k], r.action_e[:, k] * problem.motion_sigma[:, k], t, cov,
                            command=commanded[:, k], span=span)
    terms = problem.observation_terms(st)
    pred = problem.predictions(st)
    ctx = problem.sensor_context(st)
    pose = st.poses[problem.obs_knot]
    ot = log.obs_t - log.t[0]
    scov = {"time": ot, "x": pose[:, 0], "y": pose[:, 1], "heading": pose[:, 2],
            "speed": np.hypot(ctx["velocity"][:, 0], ctx["velocity"][:, 1]), "turn_rate": ctx["velocity"][:, 2],
            "distance": pred["distance"], "bearing": pred["bearing"],
            "image_angle": wrap(pred["bearing"] - problem.pan), "landmark": log.obs_landmark.astype(float)}
    lev = sighting_leverage(problem, st, rows=r)
    for name, raw, sigma, sel in (("reading", terms["reading"], problem.reading_sigma * terms["scale"], problem.r_sel),
                                  ("bearing", terms["bearing"], np.full(len(ot), problem.bearing_sigma), problem.b_sel)):
        ok = np.isfinite(raw) & sel & (terms["weight"] > 0.5)   # a mixture's outliers are explained, the gate's out
        if not ok.any():
            continue                      # a channel the log does not measure (ranges only)
        out[name] = Channel(name, (raw / sigma)[ok], raw[ok], ot[ok], {k: c[ok] for k, c in scov.items()},
                            leverage=lev[name][ok] if name in lev else None)
    return out
