"""Diagnosis of a calibrated log: ``diagnose`` in memory (a Calibration or a model), ``run`` as the command does it."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from casm_graph.analysis.before_after import compare, load_before
from casm_graph.analysis.diagnose_continuous import diagnose as diagnose_continuous
from casm_graph.analysis.diagnosis import DEFAULTS, DiagnoseOptions, Diagnosis
from casm_graph.analysis.diagnosis import diagnose as diagnose_table
from casm_graph.analysis.proposal import ProposalOptions
from casm_graph.fit import trajectory
from casm_graph.fit.calibration import Calibration
from casm_graph.io.identifiability import check_identifiable
from casm_graph.io.log import Log, LogError, load
from casm_graph.io.output import checked_out
from casm_graph.models.effects import unresolved
from casm_graph.models.model import Model
from casm_graph.report import pages as report


def diagnose(log: Log, calibration: Calibration | Model, extra_effects=(), candidates=None, workers: int = 2,
             progress=None, poses: np.ndarray | None = None, client=None, before=None,
             proposal_options: ProposalOptions | None = None, options: DiagnoseOptions = DEFAULTS) -> Diagnosis:
    """Where ``calibration`` fails on ``log`` and which effect is missing; in memory (``save`` writes DIAG).

    ``calibration`` is a :class:`Calibration` (its trajectory is the start) or a :class:`Model` (then
    ``poses`` if given, else a fresh smoother's). ``extra_effects``: user effect classes to consider;
    ``client``: a Dask ``distributed.Client`` to fit the candidates and folds on (default: a local process pool);
    ``before``: an earlier diagnosis of the log (a :class:`Diagnosis`, its DIAG directory, diagnosis.json or its dict) to
    show the change against (``before_after`` in diagnosis.json, a table and figure in the report);
    ``options``: how the residuals are tested and the candidates weighed (recorded in diagnosis.json);
    ``proposal_options``, when given, replaces ``options.proposal`` (how an unexplained verdict's equation is searched).
    """
    if proposal_options is not None:
        options = replace(options, proposal=proposal_options)
    if before is not None and not isinstance(before, (Diagnosis, dict)):
        before = load_before(before)                 # read first: a bad path fails before the computation
    if isinstance(calibration, Calibration):
        if isinstance(calibration.model, dict):
            raise LogError(f"diagnose: the {calibration.options.method} models of a 1-D log have no diagnosis")
        model = calibration.model
        poses = np.column_stack([calibration.trajectory[k] for k in ("x", "y", "theta")]) if poses is None else poses
    else:
        model = calibration
    check_identifiable(log)
    unknown = unresolved(model.effects, extra_effects)
    if unknown:
        raise LogError(f"unknown effect(s) {unknown} in the model (pass their classes as extra_effects)")
    model = model.for_log(log)
    if poses is None:
        poses = trajectory.smoothed(log, model, progress)
    if log.controls is not None:
        graph = calibration.options.command_graph if isinstance(calibration, Calibration) else None
        diag = diagnose_continuous(log, model, poses, progress=progress, extra_effects=extra_effects,
                                   candidates=candidates, options=options, graph=graph)
    else:
        diag = diagnose_table(log, model, poses, extra_effects=extra_effects, workers=workers, progress=progress,
                              candidates=candidates, client=client, options=options)
    diag.log, diag.write_report = log, report.diagnosis
    if before is not None:
        diag.before_after = compare(before.to_json() if isinstance(before, Diagnosis) else before, diag.to_json())
    return diag


def run(log_dir, model_path, out, workers: int = 2, progress=None, extra_effects=(), candidates=None,
        force: bool = False, client=None, before=None) -> Diagnosis:
    """Diagnose the model at ``model_path`` on the bundle at ``log_dir``; write DIAG to ``out`` (all or nothing)."""
    checked_out(out, force, inputs=[log_dir, model_path] + ([before] if before is not None else []))
    before = load_before(before) if before is not None else None
    model_path = Path(model_path)
    model = Model.load(model_path)
    log = load(log_dir)
    diag = diagnose(log, model, extra_effects=extra_effects, candidates=candidates, workers=workers,
                    progress=progress, poses=trajectory.from_run(log, model_path), client=client, before=before)
    if progress is not None:
        progress.stage("report", None)
    diag.save(out, force=force)
    return diag
