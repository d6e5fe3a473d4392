"""Diagnosis of a calibrated log: ``diagnose`` in memory (a Calibration or a model), ``run`` as the command does it.

One procedure for every log: the model is refitted on the log as it stands and its residual channels tested
(:mod:`casm_graph.analysis.diagnosis`); the candidate effects are fitted and scored against the same procedure
without them by the part for the model's kind of action model (:mod:`casm_graph.analysis.candidates`); the verdict
weighs them with the residual structure; the sparse regression's proposal challenges a catalog verdict or explains
what none does; look-alikes are named.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from casm_graph.analysis.before_after import compare, load_before
from casm_graph.analysis.candidates import bench
from casm_graph.analysis.correlation import correlation
from casm_graph.analysis.diagnosis import (DEFAULTS, DiagnoseOptions, Diagnosis, channel_report, discover,
                                           family_words, lookalike_words, lookalikes, open_loop_error, sighting_change,
                                           structures, verdict)
from casm_graph.analysis.proposal import ProposalOptions
from casm_graph.fit import trajectory
from casm_graph.fit.calibration import Calibration
from casm_graph.fit.residuals import channels
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
    t0 = time.perf_counter()
    o = options
    calibrated = calibration.options if isinstance(calibration, Calibration) else None
    part = bench(model.action.kind)(log, model, poses, o, extra_effects=extra_effects, candidates=candidates,
                                    workers=workers, client=client, progress=progress, calibrated=calibrated)
    chs = channels(part.problem, part.state, o.command_change)
    rep = channel_report(chs, o)
    struct = structures(rep, o)
    cands, skipped, explains, separated_by = part.score(struct)
    for c in cands:
        c.change = sighting_change(part.base_prediction, c.prediction)
    v, words = verdict(cands, struct, explains, o, last=part.last, report=rep, refit=part.refit_report)
    v, words, found = discover(v, words, chs, o.proposal, cands, explains, o.bic_support, part.challenge,
                               o.proposal_challenge, o.lookalike_bic, report=rep, visit_p=o.visit_p,
                               structure=struct)
    alike = lookalikes(cands, v, separated_by, relative=part.relative, options=o, base=part.base_prediction)
    words += family_words(cands, v) + lookalike_words(alike) + part.advice(found) + part.notes(cands)
    diag = Diagnosis(rep, cands, v, words, struct, part.fit, chs, time.perf_counter() - t0, skipped,
                     set_aside=part.set_aside, correlation=correlation(chs), lookalikes=alike,
                     predictive=open_loop_error(part.problem, part.state, part.poses), proposal=found, options=o)
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
