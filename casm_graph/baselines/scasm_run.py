"""``casm-graph calibrate --method scasm|scasm-graph`` on a 1-D log (one landmark, one command).

Writes RUN/model.json (action model ``scasm_poly``: command -> velocity, sensor model
``scasm_location_poly``: reading -> location, both in the run's own learned units), RUN/trajectory.csv
(the learned location along the walking axis as ``x``) and RUN/report.html. When the bundle is
simulated (truth_model.json) the report and model.json also carry the paper's evaluation.
"""
from __future__ import annotations

import html
import time
from pathlib import Path

import numpy as np

from casm_graph.baselines import scasm
from casm_graph.fit.calibration import CalibrateOptions, Calibration, read_truth_model, trajectory_array
from casm_graph.io.log import Log
from casm_graph.models.model import SCHEMA
from casm_graph.report.pages import STYLE, png, subplots

METHODS = ("scasm", "scasm-graph")
PAPER = {"action_rms": (29.6, 12.4), "sensor_rms": (70.4, 13.9), "consistency": (0.08, 0.06),
         "start_action_rms": 43.0, "best_quartic": 7.2, "best_cubic": 38.6}


def fit(log: Log, method: str, progress=None):
    """(result, location per pose) of ``method`` on ``log``."""
    walk = scasm.walk_of(log)
    if method == "scasm":
        if progress is not None:
            progress.stage("scasm", None)
        res = scasm.online(walk)
        return res, res.x_a
    if progress is not None:
        progress.stage("isam2", int(np.ceil(walk.t[-1] / 0.5)) + 1)
    res = scasm.graph_online(walk, progress=progress)
    return res, res.x


def model_json(res, method: str, log: Log, seconds: float, evaluation: dict | None) -> dict:
    graph = method == "scasm-graph"
    ok = np.isfinite(log.obs_reading)
    out = {
        "schema": SCHEMA,
        "action_model": {"kind": "scasm_poly", "commands": [log.control_names[0]],
                         "units": "learned location units per second (defined up to scale)",
                         **res.action.to_json(),
                         "std": [float(s) for s in res.action_std] if graph else None},
        "motion_noise": [res.motion_sigma if graph else None, 0.0, 0.0],
        "sensor_model": {"kind": "scasm_location_poly",
                         "units": "learned location units (defined up to scale and offset)",
                         **res.sensor.to_json(),
                         "std": [float(s) for s in res.sensor_std] if graph else None,
                         "location_sigma": res.sensor_sigma if graph else None,
                         "reading_sigma": None, "bearing_sigma": None,
                         "reading_range": [float(np.min(log.obs_reading[ok])), float(np.max(log.obs_reading[ok]))]},
        "effects": {},
        "fit": {"method": method, "iterations": int(getattr(res, "updates", len(res.history))),
                "seconds": round(seconds, 3), "log_likelihood": None, "converged": True,
                "constants": ({"motion_sigma": res.motion_sigma, "sensor_sigma": res.sensor_sigma} if graph else
                              {"gamma": scasm.GAMMA, "lambda": scasm.LAMBDA, "t_start": scasm.T_START})},
    }
    if evaluation is not None:
        out["fit"]["evaluation"] = evaluation
    return out


def evaluate(res, truth: dict) -> dict:
    s = scasm.score(res.action, res.sensor, truth)
    start = scasm.score(lambda c: c, res.sensor, truth)
    return {"action_rms_mm_s": s.action_rms, "sensor_rms_mm": s.sensor_rms, "scale_ratio": s.ratio,
            "consistency": s.consistency, "start_action_rms_mm_s": start.action_rms,
            "best_quartic_rms_mm_s": truth["action_model"].get("best_quartic_rms_mm_s"),
            "best_cubic_rms_mm": truth["sensor_model"].get("best_cubic_rms_mm")}


def learning_curves(history, c_scale: float, o_scale: float, truth: dict) -> np.ndarray:
    """(t, action RMS, sensor RMS) after the paper's fits, at each history entry."""
    rows = []
    for t, a, s in history:
        sc = scasm.score(scasm.PolyModel(a, c_scale), scasm.PolyModel(s, o_scale), truth)
        rows.append((t, sc.action_rms, sc.sensor_rms))
    return np.array(rows)


def figures(log: Log, res, loc: np.ndarray, truth: dict | None) -> list[str]:
    walk = scasm.walk_of(log)
    out = []
    fig, axs = subplots(1, 2, figsize=(12, 4))
    c = np.linspace(walk.command.min(), walk.command.max(), 200)
    r = np.linspace(walk.reading.min(), walk.reading.max(), 200)
    if truth is None:
        axs[0].plot(c, res.action(c), "C0", lw=2, label="learned")
        axs[1].plot(r, res.sensor(r), "C0", lw=2, label="learned")
        axs[0].set(ylabel="velocity (learned units/s)")
        axs[1].set(ylabel="location (learned units)")
    else:
        sc = scasm.score(res.action, res.sensor, truth)
        am, sm = truth["action_model"], truth["sensor_model"]
        axs[0].plot(c, sc.action_scale * res.action(c), "C0", lw=2, label="learned (best scale)")
        axs[0].plot(am["commands"], 1000 * np.asarray(am["velocities"]), "C3o", ms=4, label="true")
        off = np.mean(1000 * np.asarray(sm["distances"]) - sc.sensor_scale * res.sensor(np.asarray(sm["readings"])))
        axs[1].plot(r, off + sc.sensor_scale * res.sensor(r), "C0", lw=2, label="learned (best scale + offset)")
        axs[1].plot(sm["readings"], 1000 * np.asarray(sm["distances"]), "C3o", ms=4, label="true")
        axs[0].set(ylabel="velocity (mm/s)")
        axs[1].set(ylabel="distance (mm)")
    axs[0].set(xlabel=f"command {log.control_names[0]}", title="Action model")
    axs[1].set(xlabel="reading", title="Sensor model")
    for ax in axs:
        ax.legend()
    fig.tight_layout()
    out += ["<h2>Learned models</h2>", png(fig)]
    fig, ax = subplots(figsize=(12, 3.5))
    ax.plot(walk.t[walk.obs_step], res.sensor(walk.reading), ".", ms=1.5, color="0.6", label="x_s = S(reading)")
    ax.plot(walk.t, loc, "C0", lw=1, label="location estimate")
    ax.set(xlabel="time (s)", ylabel="location (learned units)", title="The two location estimates (paper Fig. 6)")
    ax.legend()
    out += ["<h2>Location over time</h2>", png(fig)]
    if truth is not None and res.history:
        lc = learning_curves(res.history, res.action.scale, res.sensor.scale, truth)
        fig, axs = subplots(1, 2, figsize=(12, 3.5))
        axs[0].plot(lc[:, 0], lc[:, 1])
        axs[0].axhline(truth["action_model"]["best_quartic_rms_mm_s"], color="k", ls="--", lw=0.8)
        axs[0].set(xlabel="time (s)", ylabel="mm/s", title="action model error (paper Fig. 8)", ylim=(0, 100))
        axs[1].plot(lc[:, 0], lc[:, 2])
        axs[1].axhline(truth["sensor_model"]["best_cubic_rms_mm"], color="k", ls="--", lw=0.8)
        axs[1].set(xlabel="time (s)", ylabel="mm", title="sensor model error", ylim=(0, 400))
        fig.tight_layout()
        out += ["<h2>Learning curves</h2>", png(fig)]
    return out


def calibrate(log: Log, options: CalibrateOptions, progress=None) -> Calibration:
    """Calibrate the 1-D log with ``options.method`` (scasm or scasm-graph); in memory."""
    method = options.method
    scasm.walk_of(log)                                # wrong kind of log: LogError before any work
    t0 = time.perf_counter()
    res, loc = fit(log, method, progress)
    seconds = time.perf_counter() - t0
    truth = read_truth_model(log.source)
    if truth is not None and truth.get("protocol") != "scasm_1d":
        truth = None
    evaluation = evaluate(res, truth) if truth is not None else None
    model = model_json(res, method, log, seconds, evaluation)
    poses = np.column_stack([loc, np.zeros_like(loc), np.zeros_like(loc)])

    def write_report(path: Path, cal: Calibration) -> None:
        path.write_text(report_page(log, res, loc, truth, model, method, seconds, evaluation))

    return Calibration(log=log, model=model, trajectory=trajectory_array(log.pose_times, poses, np.full_like(poses, np.nan)),
                       options=options, write_report=write_report)


def report_page(log: Log, res, loc, truth, model: dict, method: str, seconds: float, evaluation) -> str:
    """report.html of a 1-D calibration: the paper's evaluation when the truth is known, the models, the walk."""
    facts = [("method", method), ("seconds", f"{seconds:.2f}"), ("frames", log.steps),
             ("readings", int(np.isfinite(log.obs_reading).sum()))]
    facts += [(k, v) for k, v in model["fit"]["constants"].items()]
    rows = ""
    if evaluation is not None:
        p = PAPER
        rows = ("<h2>The paper's evaluation</h2><table><tr><th></th><th>this run</th><th>paper (10 trials)</th></tr>"
                f"<tr><th>action RMS after scale fit (mm/s)</th><td>{evaluation['action_rms_mm_s']:.1f}</td>"
                f"<td>{p['action_rms'][0]} &plusmn; {p['action_rms'][1]}</td></tr>"
                f"<tr><th>sensor RMS after scale + offset fit (mm)</th><td>{evaluation['sensor_rms_mm']:.1f}</td>"
                f"<td>{p['sensor_rms'][0]} &plusmn; {p['sensor_rms'][1]}</td></tr>"
                f"<tr><th>| |scale ratio| - 1 |</th><td>{evaluation['consistency']:.3f}</td>"
                f"<td>{p['consistency'][0]} &plusmn; {p['consistency'][1]}</td></tr>"
                f"<tr><th>start model A0(c) = c (mm/s)</th><td>{evaluation['start_action_rms_mm_s']:.1f}</td>"
                f"<td>{p['start_action_rms']}</td></tr>"
                f"<tr><th>best possible quartic / cubic</th><td>{evaluation['best_quartic_rms_mm_s']:.1f} / "
                f"{evaluation['best_cubic_rms_mm']:.1f}</td><td>{p['best_quartic']} / {p['best_cubic']}</td></tr></table>")
    info = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in facts)
    body = [f"<h1>casm-graph calibration: {method}</h1><table>{info}</table>", rows, *figures(log, res, loc, truth)]
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{method}</title>"
            f"<style>{STYLE}</style></head><body>{''.join(body)}</body></html>")
