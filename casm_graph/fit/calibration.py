"""The result of a calibration as a user holds it: model, trajectory, summary, and ``save`` to a run directory.

``casm_graph.pipeline.calibrate`` returns a :class:`Calibration` in memory and writes nothing; ``save`` writes
RUN exactly as ``casm-graph calibrate`` does (model.json, trajectory.csv, report.html), all or nothing.
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Callable

import numpy as np

from casm_graph.fit.continuous import CommandGraphOptions
from casm_graph.fit.result import Fit
from casm_graph.fit.methods.graph import GraphOptions
from casm_graph.io.log import Log
from casm_graph.io.output import atomic_dir, json_text
from casm_graph.models.model import Model

TRAJECTORY_FIELDS = ("t", "x", "y", "theta", "sx", "sy", "stheta")


def version() -> str:
    try:
        return metadata.version("casm-graph")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class CalibrateOptions:
    """What a calibration was asked to do; recorded in model.json ``fit.options``.

    ``effects`` holds catalog names or :class:`casm_graph.Effect` subclasses; ``regions`` is the
    regional_motion_noise grid ("NX,NY" or "NX,NY,X0,Y0,X1,Y1", default 3,2 around the landmarks).
    """

    method: str = "graph"
    sensor_degree: int = 3
    effects: tuple = ()
    seed: int = 0
    regions: str | None = None
    graph: GraphOptions = field(default_factory=GraphOptions)   # the action-table graph's search (graph, graph-em)
    command_graph: CommandGraphOptions = field(default_factory=CommandGraphOptions)   # the continuous-command graph's search
    max_sensor_degree: int = 6         # the graph method raises the sensor degree up to this when the data demand
    sensor_basis: str = "auto"         # the curve's variable: "distance" (the paper's), "inverse_distance" (a size),
                                       # or "auto": d, and 1/d competing when the fit in d misses near the landmarks
    cross_terms: bool | str = "auto"   # ``v, w`` commands: the turn map also linear in ``v`` (unequal wheels);
                                       # "auto": the graph method keeps it when BIC supports it
    step_heading: str = "auto"         # the heading a command step moves along: "start" (the paper's step), "middle"
                                       # (the chord of the arc a held command drives) or "auto": an action table's
                                       # steps the start, continuous commands' the middle

    def to_json(self) -> dict:
        return {"method": self.method, "sensor_degree": self.sensor_degree, "seed": self.seed,
                "effects": [e if isinstance(e, str) else e.name for e in self.effects], "regions": self.regions,
                "max_sensor_degree": self.max_sensor_degree, "sensor_basis": self.sensor_basis,
                "cross_terms": self.cross_terms, "step_heading": self.step_heading, "graph": self.graph.to_json(),
                "command_graph": self.command_graph.to_json()}


def cross_term_words(cross: dict) -> str:
    """One line on the turn map's term in v from model.json's ``fit.cross_term``: its value, std, and whether
    the calibration kept it."""
    sd = cross.get("w_per_v_std")
    return (f"turn rate per forward speed (unequal wheels): {cross['w_per_v']:+.4g} rad/s per m/s"
            + (f" (std {sd:.2g})" if sd is not None else "") + (", kept" if cross["kept"] else ", not kept")
            + f" (delta BIC {cross['delta_bic']:,.1f})")


def read_truth_model(log_dir) -> dict | None:
    """truth_model.json from a simulated bundle, for reports' comparisons only (never for fitting)."""
    if log_dir is None:
        return None
    p = Path(log_dir) / "truth_model.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None


def trajectory_array(t: np.ndarray, poses: np.ndarray, std: np.ndarray) -> np.ndarray:
    """A structured array with fields ``t,x,y,theta,sx,sy,stheta`` (one row per pose)."""
    out = np.empty(len(t), dtype=[(f, float) for f in TRAJECTORY_FIELDS])
    for name, col in zip(TRAJECTORY_FIELDS, np.column_stack([t, poses, std]).T):
        out[name] = col
    return out


def write_trajectory(path: Path, trajectory: np.ndarray) -> None:
    """trajectory.csv: ``t,x,y,theta`` and their standard deviations (empty where unknown)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(TRAJECTORY_FIELDS)
        for row in trajectory:
            w.writerow([f"{v:.6f}" if np.isfinite(v) else "" for v in row.tolist()])


@dataclass
class Calibration:
    """One calibrated log: ``model`` (as in model.json), ``trajectory`` (structured array), how the fit went."""

    log: Log
    model: Model | dict                  # dict for the 1-D SCASM models, whose kinds model.json documents
    trajectory: np.ndarray
    options: CalibrateOptions
    fit: Fit | None = None               # the method's full result (cost trace, stages, poses)
    write_report: Callable[[Path, "Calibration"], None] | None = field(default=None, repr=False)
    command: str | None = None           # the command line, when run from one

    @property
    def model_json(self) -> dict:
        """model.json's content, with the options, version, log path and command recorded under ``fit``."""
        data = self.model if isinstance(self.model, dict) else self.model.to_json()
        run = {"options": self.options.to_json(), "version": version(), "log": self.log.source,
               "command": self.command}
        if self.log.held_commands is not None:
            run["held_commands"] = self.log.held_commands
        return {**data, "fit": {**data.get("fit", {}), **run}}

    def summary(self) -> str:
        """How good the fit is, in units, then the models and the effects: a page of text."""
        if isinstance(self.model, dict):
            fit = self.model.get("fit", {})
            lines = [f"casm-graph calibration by {fit.get('method')} of a 1-D log ({self.log.steps} frames)",
                     f"  {fit.get('iterations')} updates in {fit.get('seconds')} s"]
            lines += [f"  {k}: {v:.4g}" for k, v in fit.get("evaluation", {}).items() if isinstance(v, float)]
            return "\n".join(lines)
        m, log = self.model, self.log
        fit = m.fit
        kind = m.action.describe()
        lines = [f"casm-graph calibration of {log.source or 'a log'} by {fit.get('method', self.options.method)}",
                 f"  log: {kind}, {log.steps} steps, {len(log.obs_t)} sightings, {log.minutes:.1f} min"
                 + (" (the {rows} rows of commands.csv held over {steps:,} steps, median {step:.3g} s, at the "
                    "sightings' times)".format(**log.held_commands) if log.held_commands is not None else ""),
                 f"  fit: {'converged' if fit.get('converged') else 'NOT converged'} after {fit.get('iterations')} "
                 f"iterations in {fit.get('seconds', 0):.1f} s, log-likelihood {fit.get('log_likelihood', float('nan')):,.1f}",
                 f"  sensor: reading sigma {m.noise_text('reading')} (reading units), bearing sigma "
                 f"{m.noise_text('bearing')} rad, over distances {m.distance_range[0]:.2f}-{m.distance_range[1]:.2f} m",
                 ("  reading = " + " + ".join(f"{c:.4g} d^{i}" for i, c in enumerate(m.reading_poly))
                  if m.has("reading") else "  reading: not measured (a bearing-only log)"),
                 "  motion noise per step: " + ", ".join(f"{s:.3g}" for s in m.motion_noise) + " (m, m, rad)"]
        if m.action.std_summary() is not None:
            lines.append("  {}: {}".format(*m.action.std_summary()))
        if fit.get("cross_term"):
            lines.append("  " + cross_term_words(fit["cross_term"]))
        pose_sd = np.sqrt(np.nanmean(self.trajectory["sx"] ** 2 + self.trajectory["sy"] ** 2)) \
            if np.isfinite(self.trajectory["sx"]).any() else float("nan")
        lines.append(f"  trajectory: RMS position std {pose_sd:.3f} m")
        std = fit.get("effects_std", {})
        for name, params in m.effects.items():
            vals = ", ".join(f"{k} {v:.4g}" + (f" (std {std[name][k]:.2g})" if k in std.get(name, {}) else "")
                             for k, v in params.items() if isinstance(v, (int, float)))
            lines.append(f"  effect {name}: {vals or '(see model.json)'}")
        return "\n".join(lines)

    def save(self, out, force: bool = False) -> Path:
        """Write RUN (model.json, trajectory.csv, report.html) all or nothing; ``out`` must be new or empty."""
        inputs = [self.log.source] if self.log.source else []
        with atomic_dir(out, force=force, inputs=inputs) as tmp:
            (tmp / "model.json").write_text(json_text(self.model_json))
            write_trajectory(tmp / "trajectory.csv", self.trajectory)
            if self.write_report is not None:
                self.write_report(tmp / "report.html", self)
        return Path(out)
