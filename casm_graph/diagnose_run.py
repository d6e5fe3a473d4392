"""``casm-graph diagnose``: load the log and model, find a start trajectory, diagnose, write DIAG."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from . import report
from .diagnose import Diagnosis, diagnose
from .effects import REGISTRY
from .log import Log, LogError, load
from .model import Model


def _trajectory_csv(log: Log, model_path: Path) -> np.ndarray | None:
    """(T+1, 3) poses from RUN/trajectory.csv beside the model, when it is there and fits the log."""
    tr = model_path.parent / "trajectory.csv"
    if tr.is_file():
        with open(tr) as f:
            rows = list(csv.DictReader(f))
        if len(rows) == log.steps + 1:
            try:
                return np.array([[float(r["x"]), float(r["y"]), float(r["theta"])] for r in rows])
            except (KeyError, ValueError):
                pass
    return None


def start_trajectory(log: Log, model: Model, model_path: Path) -> np.ndarray:
    """(T+1, 3) poses: RUN/trajectory.csv beside the model when it fits the log, else the EKF smoother's."""
    poses = _trajectory_csv(log, model_path)
    if poses is not None:
        return poses
    from .methods.ekfs_em import fit as ekfs_fit
    return ekfs_fit(log, model, max_iterations=1).poses


def check_compatible(log: Log, model: Model, source: str) -> None:
    missing = sorted(set(log.action_ids.tolist()) - set(model.action_ids.tolist()))
    if missing:
        raise LogError(f"{source}: the model has no velocity for action(s) {missing[:10]} that the log runs")


def run(log_dir, model_path, out, workers: int = 2, progress=None, extra_effects=(), candidates=None) -> Diagnosis:
    """Diagnose the model at ``model_path`` on the bundle at ``log_dir``; write DIAG files to ``out``."""
    model_path = Path(model_path)
    model = Model.load(model_path)
    log = load(log_dir)
    if log.controls is not None:
        diag = _continuous(log, model, model_path, log_dir, progress)
        return _write(diag, log, out, progress)
    check_compatible(log, model, model_path.name)
    model = model.with_(velocities=model.velocities[np.searchsorted(model.action_ids, log.action_ids)],
                        action_ids=log.action_ids, velocity_std=None)
    unknown = [n for n in model.effects if n not in REGISTRY and n not in {c.name for c in extra_effects}]
    if unknown:
        raise LogError(f"{model_path.name}: unknown effect(s) {unknown} in the model (pass their classes as extra_effects)")
    if progress is not None:
        progress.stage("start trajectory", None)
    poses = start_trajectory(log, model, model_path)
    diag = diagnose(log, model, poses, extra_effects=extra_effects, workers=workers, progress=progress,
                    candidates=candidates)
    return _write(diag, log, out, progress)


def _continuous(log: Log, model: Model, model_path: Path, log_dir, progress) -> Diagnosis:
    """Continuous commands: the model's trajectory.csv (or a fresh fit's poses), then the continuous diagnosis."""
    from . import continuous
    from .diagnose_continuous import diagnose as diagnose_continuous
    if model.command is None:
        raise LogError(f"{model_path.name}: {log_dir} has continuous commands but the model has no command map "
                       f"(action_model.kind 'command_poly'); calibrate this log first")
    poses = _trajectory_csv(log, model_path)
    if poses is None:
        if progress is not None:
            progress.stage("start trajectory", None)
        poses = continuous.fit(log, model, marginals=False).poses
    return diagnose_continuous(log, model, poses, progress=progress)


def _write(diag: Diagnosis, log: Log, out, progress) -> Diagnosis:
    if progress is not None:
        progress.stage("report", None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    diag.save(out / "diagnosis.json")
    report.diagnosis(out / "report.html", log, diag)
    return diag
