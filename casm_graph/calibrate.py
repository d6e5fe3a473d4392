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
from . import augmented, effect_fit
from .effects import get as get_effect
from .log import Log, LogError, load
from .methods import METHODS, Fit, Progress
from .model import paper_start

SCASM_METHODS = ("scasm", "scasm-graph")      # casm_graph/scasm_run.py


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


def with_effects(log: Log, fit: Fit, effects, seed: int = 0, progress: Progress | None = None) -> Fit:
    """Refit ``fit`` with ``effects`` added (warm start); std of poses, table and polynomial from the effect graph."""
    import time
    t0 = time.perf_counter()
    if progress is not None:
        progress.stage("effects", effect_fit.ROUNDS)
    ef = effect_fit.fit(log, fit.model, fit.poses, effects, seed=seed,
                        on_iteration=(lambda c: progress.step(0, cost=c)) if progress is not None else None)
    cov_p, cov_t = augmented.marginals(ef.problem, ef.state)
    A, D = ef.problem.A, ef.problem.D
    sd = np.sqrt(np.clip(np.diag(cov_t), 0, None))
    effect_std = {}
    for e, s in zip(ef.effects, ef.problem.slices):
        if not e.noise_only:
            cols = [3 * A + D + int(np.flatnonzero(ef.problem.ls_index == i)[0]) for i in range(s.start, s.stop)]
            effect_std[e.name] = {p: float(sd[c]) for p, c in zip(e.params, cols)}
    from .methods.graph import world_std
    pose_std = world_std(ef.poses, np.sqrt(np.einsum("kii->ki", cov_p)), cov_p[:, :2, :2])
    model = ef.model.with_(velocity_std=sd[:3 * A].reshape(-1, 3), reading_poly_std=sd[3 * A:3 * A + D],
                           reading_poly_cov=cov_t[3 * A:3 * A + D, 3 * A:3 * A + D],
                           fit={**fit.model.fit, "iterations": fit.model.fit.get("iterations", 0) + ef.iterations,
                                "seconds": round(fit.model.fit.get("seconds", 0) + time.perf_counter() - t0, 3),
                                "log_likelihood": ef.log_likelihood, "effects_std": effect_std})
    return Fit(model=model, poses=ef.poses, pose_std=pose_std, cost=fit.cost + ef.cost,
               stages=fit.stages + ["effects"] * len(ef.cost), iterations=fit.iterations + ef.iterations,
               converged=fit.converged, log_likelihood=ef.log_likelihood,
               notes={**fit.notes, "base_log_likelihood": fit.log_likelihood})


def parse_regions(text: str | None, log: Log):
    """The regional_motion_noise grid from "NX,NY" or "NX,NY,X0,Y0,X1,Y1" (None: the default around the landmarks)."""
    from .effects.regional_motion_noise import Regions
    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (2, 6) or v[0] < 1 or v[1] < 1 or v[0] != int(v[0]) or v[1] != int(v[1]) \
            or (len(v) == 6 and not (v[4] > v[2] and v[5] > v[3])):
        raise LogError(f"--regions {text!r}: give NX,NY or NX,NY,X0,Y0,X1,Y1 (whole counts >= 1, X1 > X0, Y1 > Y0)")
    grid = (int(v[0]), int(v[1]))
    if len(v) == 2:
        return Regions.around_landmarks(log, grid)
    return Regions(tuple(v[2:]), grid)


def run(log_dir: str | Path, out: str | Path, method: str = "graph", sensor_degree: int = 3,
        effects: tuple[str, ...] = (), seed: int = 0, progress: Progress | None = None,
        regions: str | None = None) -> tuple[Log, Fit]:
    """Calibrate the bundle at ``log_dir`` and write the run to ``out``; bad input raises LogError first.

    ``regions`` ("NX,NY" or "NX,NY,X0,Y0,X1,Y1") is the grid of the regional_motion_noise effect
    (default 3,2 around the landmarks)."""
    if method in SCASM_METHODS:               # 1-D logs: their own model kinds and report
        from . import scasm_run
        return scasm_run.run(log_dir, out, method, progress=progress)
    if method not in METHODS:
        raise LogError(f"unknown method {method!r} (known: {', '.join(sorted(METHODS))})")
    classes = [get_effect(e) if isinstance(e, str) else e for e in effects]   # unknown names fail first
    if not 1 <= sensor_degree <= 6:
        raise LogError(f"--sensor-degree must be between 1 and 6 (got {sensor_degree})")
    log = load(log_dir)
    if log.controls is None:
        for cls in classes:
            why = cls(log).applicable(log)
            if why:
                raise LogError(f"effect {cls.name!r} cannot be fitted on {log_dir}: {why}")
    else:                                   # continuous commands: the command-model graph
        from . import continuous, command_report
        if method != "graph":
            raise LogError(f"--method {method}: continuous commands (commands.csv 'v,w') are calibrated "
                           f"by the graph method only")
        continuous.check_effects(cls.name for cls in classes)
        grid = parse_regions(regions, log)
        start = continuous.start_model(log, sensor_degree)
        if classes:
            fit = continuous.fit_with_effects(log, start, [cls.name for cls in classes], seed=seed, progress=progress,
                                              regions=grid)
        else:
            fit = continuous.fit(log, start, seed=seed, progress=progress)
        if progress is not None:
            progress.stage("report", None)
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        fit.model.save(out / "model.json")
        write_trajectory(out / "trajectory.csv", log.pose_times, fit.poses, fit.pose_std)
        command_report.calibration(out / "report.html", log, fit)
        return log, fit
    start = paper_start(log, sensor_degree)
    fit = METHODS[method](log, start, seed=seed, progress=progress)
    if classes:
        fit = with_effects(log, fit, classes, seed=seed, progress=progress)
    if progress is not None:
        progress.stage("report", None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fit.model.save(out / "model.json")
    write_trajectory(out / "trajectory.csv", log.pose_times, fit.poses, fit.pose_std)
    report.calibration(out / "report.html", log, fit, fit.pose_std, read_truth_model(Path(log_dir)))
    return log, fit
