"""The trajectory a fixed model gives a log: where ``diagnose`` and ``uncertainty`` start when the user gives a
model without its run's poses. A table model takes one pass of the EKF smoother, a command map one graph fit."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from casm_graph.fit import continuous
from casm_graph.fit.methods.ekfs_em import fit as ekfs_fit
from casm_graph.io.log import Log
from casm_graph.models.model import Model


def _ekfs_pass(log: Log, model: Model) -> np.ndarray:
    return ekfs_fit(log, model, max_iterations=1).poses


def _command_graph(log: Log, model: Model) -> np.ndarray:
    return continuous.fit(log, model, marginals=False, options=continuous.options_of(model)).poses


SMOOTHERS = {"table": _ekfs_pass, "command_poly": _command_graph}     # by the model's ``action.kind``


def smoothed(log: Log, model: Model, progress=None) -> np.ndarray:
    """(T+1, 3) poses of ``log`` under ``model`` (made ready for the log by :meth:`Model.for_log`)."""
    if progress is not None:
        progress.stage("start trajectory", None)
    return SMOOTHERS[model.action.kind](log, model)


def from_run(log: Log, model_path: Path) -> np.ndarray | None:
    """(T+1, 3) poses from RUN/trajectory.csv beside the model, when it is there and fits the log."""
    tr = Path(model_path).parent / "trajectory.csv"
    if tr.is_file():
        with open(tr) as f:
            rows = list(csv.DictReader(f))
        if len(rows) == log.steps + 1:
            try:
                return np.array([[float(r["x"]), float(r["y"]), float(r["theta"])] for r in rows])
            except (KeyError, ValueError):
                pass
    return None
