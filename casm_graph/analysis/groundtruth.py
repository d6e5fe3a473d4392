"""Checks of a continuous-command calibration against ground truth (Vicon on the MRCLAM robots).

Never used by the fit: truth.csv only enters here, to say how far the learned command maps and
trajectory are from what the truth shows.

* :func:`truth_fit`: the same command-model form fitted with the poses held at the truth, i.e. the
  map a perfect trajectory would give; the learned maps are compared with it over the commands the
  robot actually ran (RMS, as a fraction of that velocity's range).
* :func:`baseline_trajectories`: the graph trajectory under the uncalibrated models (velocity =
  command, reading = distance; noise levels still estimated), and dead reckoning on the raw
  commands from the true start pose.
"""
from __future__ import annotations

import numpy as np

import factors
from casm_graph.fit import continuous as CT
from casm_graph.fit.result import Fit, Progress
from casm_graph.io.log import Log, LogError
from casm_graph.models.command_model import CommandModel


def truth_fit(log: Log, form: CommandModel, knot_dt: float = 1.0, iterations: int = 8) -> CommandModel:
    """``form``'s coefficients that best carry the truth from knot to knot (Gauss-Newton, robust scale)."""
    if log.truth is None:
        raise LogError("truth.csv: needed to fit the command model against ground truth")
    lay = CT.layout(log, knot_dt)
    P = log.truth[lay.knots, 1:]
    bv, by, bw = form.basis(log.controls, log.dt)
    Bv, By, Bw = bv[lay.seg_idx], by[lay.seg_idx], bw[lay.seg_idx]
    w = 1.0 / np.sqrt(np.maximum(lay.seg_time, 1e-9))[:, None]
    p = form.params.copy()
    scale = np.ones(3)
    for it in range(iterations):
        e, J = factors.command.error(P[:-1], P[1:], p, Bv, Bw, lay.seg_dt, By, form.lead)
        if it == 2:          # per-axis scale from the residuals once the fit has settled
            scale = 1.4826 * np.median(np.abs(e * w), axis=0) + 1e-9
        ww = w / scale
        A = (J[2] * ww[:, :, None]).reshape(-1, len(p))
        step, *_ = np.linalg.lstsq(A, -(e * ww).ravel(), rcond=None)
        p = p + step
    return form.with_params(p)


def map_errors(learned: CommandModel, ref: CommandModel, controls: np.ndarray, dt: np.ndarray) -> dict:
    """RMS difference of the two maps over the commands run (time-weighted), absolute and per range of ``ref``:
    ``v`` the forward map, ``w`` the turn map, ``vy`` the sideways one (``vx, vy, w`` commands)."""
    a, b = learned.velocities(controls), ref.velocities(controls)
    out = {}
    for name, j in (("v", 0), ("w", 2), *((("vy", 1),) if learned.sizes[1] else ())):
        rms = float(np.sqrt(np.sum(dt * (a[:, j] - b[:, j]) ** 2) / np.sum(dt)))
        span = float(np.ptp(b[:, j]))
        out[name] = {"rms": rms, "range": span, "fraction": rms / span if span > 0 else float("nan")}
    return out


def position_rms(poses: np.ndarray, truth: np.ndarray) -> float:
    """RMS of the position error against truth rows (t, x, y, theta) at the same pose times."""
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, 1:3]) ** 2, axis=1))))


def trajectory_rms(trajectory: dict, truth: np.ndarray) -> float:
    """:func:`position_rms` of a calibration's trajectory (its ``x``, ``y`` columns, one row per pose)."""
    return position_rms(np.column_stack([trajectory["x"], trajectory["y"]]), truth)


def baseline_trajectories(log: Log, fit: Fit, progress: Progress | None = None) -> dict:
    """Poses of the identity-model graph (from the fit's own start) and of raw dead reckoning."""
    progress = progress or Progress()
    ident = CT.identity_model(log, fit.notes["start_model"])
    o = CT.options_of(fit.model)                 # the calibration's graph
    full = CT.layout(log, o.full_knot_dt)
    start = fit.notes["start_poses"]
    progress.stage("identity graph", o.coarse_rounds)
    model, kp, *_ = CT.optimise_rounds(log, full, ident, start[full.knots], o.coarse_rounds, o.full_iterations,
                                       0, "identity", [], [], progress, freeze=True)
    graph = CT.fill_in(log, model, full.knots, kp)
    dr = None
    if log.truth is not None:
        dr = CT.dead_reckon(log.controls, log.dt, ident, log.truth[0, 1:])
    return {"identity_graph": graph, "dead_reckoning": dr, "identity_model": model}


def evaluate(log: Log, fit: Fit, progress: Progress | None = None) -> dict:
    """All the checks of issue 7 for one calibrated log with truth, as plain numbers."""
    learned = fit.model.command
    ref = truth_fit(log, learned)
    errs = map_errors(learned, ref, log.controls, log.dt)
    base = baseline_trajectories(log, fit, progress)
    cal_dr = CT.dead_reckon(log.controls, log.dt, fit.model, log.truth[0, 1:])
    out = {"map_error": errs,
           "learned": learned.to_json()["coefficients"], "vicon_fit": ref.to_json()["coefficients"],
           "position_rms": {"calibrated_graph": position_rms(fit.poses, log.truth),
                            "identity_graph": position_rms(base["identity_graph"], log.truth),
                            "dead_reckoning_raw": position_rms(base["dead_reckoning"], log.truth),
                            "dead_reckoning_calibrated": position_rms(cal_dr, log.truth)},
           "sensor": {"reading_poly": fit.model.reading_poly.tolist(), "reading_sigma": fit.model.reading_sigma,
                      "bearing_sigma": fit.model.bearing_sigma},
           "minutes": log.minutes, "observations": int(len(log.obs_t)),
           "seconds": fit.model.fit.get("seconds")}
    pr = out["position_rms"]
    out["ratio_to_identity"] = pr["calibrated_graph"] / pr["identity_graph"]
    out["meets"] = {"turn": errs["w"]["fraction"] < 0.05, "speed": errs["v"]["fraction"] < 0.10,
                    "half_identity": out["ratio_to_identity"] <= 0.5}
    out["_trajectories"] = {"identity_graph": base["identity_graph"], "dead_reckoning": base["dead_reckoning"],
                            "dead_reckoning_calibrated": cal_dr}
    out["_vicon_model"] = ref
    return out

