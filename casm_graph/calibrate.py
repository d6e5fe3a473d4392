"""``casm-graph calibrate``: load a log, fit it with a method from the registry, write the run.

The run directory gets model.json (INTERFACE section 3), trajectory.csv (``t,x,y,theta`` and the
marginal standard deviations ``sx,sy,stheta`` in the map frame) and report.html.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from . import report
from .log import Log, LogError, load
from .methods import METHODS, Fit, Progress
from .model import paper_start


def write_trajectory(path: Path, t: np.ndarray, poses: np.ndarray, std: np.ndarray) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "theta", "sx", "sy", "stheta"])
        for ti, p, s in zip(t, poses, std):
            w.writerow([f"{ti:.6f}", *(f"{v:.6f}" for v in p), *("" if np.isnan(v) else f"{v:.6f}" for v in s)])


def read_truth_model(log_dir: Path) -> dict | None:
    """truth_model.json from a simulated bundle, for the report's comparisons only (never for fitting)."""
    p = Path(log_dir) / "truth_model.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError:
        return None


def run(log_dir: str | Path, out: str | Path, method: str = "graph", sensor_degree: int = 3,
        effects: tuple[str, ...] = (), seed: int = 0, progress: Progress | None = None) -> tuple[Log, Fit]:
    """Calibrate the bundle at ``log_dir`` and write the run to ``out``; bad input raises LogError first."""
    if method not in METHODS:
        raise LogError(f"unknown method {method!r} (known: {', '.join(sorted(METHODS))})")
    if effects:
        raise LogError(f"unknown effect {effects[0]!r} (the effect catalog is empty in this version)")
    if not 1 <= sensor_degree <= 6:
        raise LogError(f"--sensor-degree must be between 1 and 6 (got {sensor_degree})")
    log = load(log_dir)
    start = paper_start(log, sensor_degree)
    fit = METHODS[method](log, start, seed=seed, progress=progress)
    if progress is not None:
        progress.stage("report", None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fit.model.save(out / "model.json")
    write_trajectory(out / "trajectory.csv", log.pose_times, fit.poses, fit.pose_std)
    report.calibration(out / "report.html", log, fit, fit.pose_std, read_truth_model(Path(log_dir)))
    return log, fit
