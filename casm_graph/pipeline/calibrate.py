"""Calibration: a log and options in, a :class:`~casm_graph.fit.calibration.Calibration` out (in memory).

``calibrate`` picks the method from the registry, fits the log, adds the requested effects and
returns the result; ``Calibration.save`` writes the run directory. ``run`` is the two together, as
``casm-graph calibrate`` does them.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from casm_graph.baselines import scasm_run
from casm_graph.fit import continuous, effect_fit
from casm_graph.fit.calibration import CalibrateOptions, Calibration, read_truth_model, trajectory_array
from casm_graph.fit.methods import METHODS, Fit, Progress
from casm_graph.fit.methods.graph import world_std
from casm_graph.graph import augmented
from casm_graph.io.identifiability import check_identifiable
from casm_graph.io.log import Log, LogError, load
from casm_graph.io.output import checked_out
from casm_graph.models.effects import get as get_effect
from casm_graph.models.effects.regional_motion_noise import Regions
from casm_graph.models.model import paper_start
from casm_graph.report import command as command_report
from casm_graph.report import pages as report
from factors.reading import BASES

SCASM_METHODS = scasm_run.METHODS             # 1-D logs: their own model kinds and report
CONTINUOUS_METHODS = ("graph", "graph-em", "ekfs-em", "ekfs-em-learned")   # the methods with a command-map action model


def with_effects(log: Log, fit: Fit, effects, seed: int = 0, progress: Progress | None = None) -> Fit:
    """Refit ``fit`` with ``effects`` added (warm start); std of poses, table and polynomial from the effect graph."""
    t0 = time.perf_counter()
    if progress is not None:
        progress.stage("effects", effect_fit.ROUNDS)
    keep = np.ones(len(log.obs_t), bool)           # the base fit's outliers stay out, as they did there
    keep[np.asarray(fit.notes.get("outliers_pruned", []), int)] = False
    ef = effect_fit.fit(log, fit.model, fit.poses, effects, seed=seed, obs_mask=keep,
                        on_iteration=(lambda c: progress.step(0, cost=c)) if progress is not None else None)
    cov_p, cov_t = augmented.marginals(ef.problem, ef.state)
    na, D = ef.problem.n_action, ef.problem.D
    sd = np.sqrt(np.clip(np.diag(cov_t), 0, None))
    effect_std = {}
    for e, s in zip(ef.effects, ef.problem.slices):
        if not e.noise_only:
            cols = [na + D + int(np.flatnonzero(ef.problem.ls_index == i)[0]) for i in range(s.start, s.stop)]
            effect_std[e.name] = {p: float(sd[c]) for p, c in zip(e.params, cols)}
    pose_std = world_std(ef.poses, np.sqrt(np.einsum("kii->ki", cov_p)), cov_p[:, :2, :2])
    model = ef.model.with_(velocity_std=sd[:na].reshape(-1, 3), reading_poly_std=sd[na:na + D],
                           reading_poly_cov=cov_t[na:na + D, na:na + D],
                           fit={**fit.model.fit, "iterations": fit.model.fit.get("iterations", 0) + ef.iterations,
                                "seconds": round(fit.model.fit.get("seconds", 0) + time.perf_counter() - t0, 3),
                                "log_likelihood": ef.log_likelihood, "effects_std": effect_std})
    return Fit(model=model, poses=ef.poses, pose_std=pose_std, cost=fit.cost + ef.cost,
               stages=fit.stages + ["effects"] * len(ef.cost), iterations=fit.iterations + ef.iterations,
               converged=fit.converged, log_likelihood=ef.log_likelihood,
               notes={**fit.notes, "base_log_likelihood": fit.log_likelihood})


def parse_regions(text: str | None, log: Log):
    """The regional_motion_noise grid from "NX,NY" or "NX,NY,X0,Y0,X1,Y1" (None: the default around the landmarks)."""
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


def check_request(options: CalibrateOptions) -> list:
    """The effect classes ``options`` ask for; an unknown method or effect or a bad degree is a LogError (before
    any work, and before the log is even read when the command line asks)."""
    if options.method not in METHODS and options.method not in SCASM_METHODS:
        raise LogError(f"unknown method {options.method!r} (known: {', '.join(sorted([*METHODS, *SCASM_METHODS]))})")
    classes = [get_effect(e) if isinstance(e, str) else e for e in options.effects]
    if not 1 <= options.sensor_degree <= 6:
        raise LogError(f"--sensor-degree must be between 1 and 6 (got {options.sensor_degree})")
    if not 1 <= options.max_sensor_degree <= 6:
        raise LogError(f"--max-sensor-degree must be between 1 and 6 (got {options.max_sensor_degree})")
    if options.sensor_basis not in (*BASES, "auto"):
        raise LogError(f"--sensor-basis must be one of auto, {', '.join(BASES)} (got {options.sensor_basis!r})")
    if options.sensor_basis not in ("distance", "auto") and options.method not in ("graph", "graph-em"):
        raise LogError(f"--sensor-basis {options.sensor_basis}: the {options.method} method fits a polynomial in the "
                       f"distance only; use --method graph or graph-em")
    return classes


def start_basis(options: CalibrateOptions) -> str:
    """The sensor curve's variable a calibration starts in ("auto" starts in the distance)."""
    return "distance" if options.sensor_basis == "auto" else options.sensor_basis


def calibrate(log: Log, options: CalibrateOptions | None = None, progress: Progress | None = None,
              command: str | None = None, **kw) -> Calibration:
    """Calibrate ``log`` as ``options`` say (or keyword arguments of :class:`CalibrateOptions`); writes nothing.

    Bad requests (unknown method or effect, an effect the log cannot carry) raise LogError before any work.
    """
    options = replace(options if options is not None else CalibrateOptions(), **kw)
    options = replace(options, effects=tuple(options.effects))
    classes = check_request(options)
    check_identifiable(log, options.sensor_degree, options.method)
    if options.method in SCASM_METHODS:
        cal = scasm_run.calibrate(log, options, progress=progress)
        cal.command = command
        return cal
    if log.controls is None:
        for cls in classes:
            why = cls(log).applicable(log)
            if why:
                raise LogError(f"effect {cls.name!r} cannot be fitted on {log.source or 'this log'}: {why}")
        start = paper_start(log, options.sensor_degree, start_basis(options))
        mixture = options.method == "graph" and any(cls.name == "false_detections" for cls in classes)
        extra = {"options": options.graph} if options.method in ("graph", "graph-em") else {}
        if options.method == "graph":
            extra["max_sensor_degree"] = options.max_sensor_degree
            extra["free_basis"] = options.sensor_basis == "auto" and options.max_sensor_degree > options.sensor_degree
        fit = METHODS[options.method](log, start, seed=options.seed, progress=progress,
                                      **({"mixture": True} if mixture else {}), **extra)
        if classes:
            fit = with_effects(log, fit, classes, seed=options.seed, progress=progress)
        truth = read_truth_model(log.source)

        def write_report(path: Path, cal: Calibration) -> None:
            report.calibration(path, log, fit, fit.pose_std, truth, cal)
    else:                                   # continuous commands: the command-model graph
        if options.method not in CONTINUOUS_METHODS:
            raise LogError(f"--method {options.method}: continuous commands (commands.csv 'v,w') are calibrated "
                           f"by {', '.join(CONTINUOUS_METHODS)}")
        continuous.check_effects(options.effects, log)
        if classes and options.method != "graph":
            raise LogError(f"--method {options.method}: effects on continuous commands are fitted by the graph method")
        grid = parse_regions(options.regions, log)
        start = continuous.start_model(log, options.sensor_degree, basis=start_basis(options))
        if options.method != "graph":
            fit = METHODS[options.method](log, start, seed=options.seed, progress=progress)
        elif classes:
            fit = continuous.fit_with_effects(log, start, list(options.effects), seed=options.seed,
                                              progress=progress, regions=grid, options=options.command_graph)
        else:
            fit = continuous.fit(log, start, seed=options.seed, progress=progress, options=options.command_graph)

        def write_report(path: Path, cal: Calibration) -> None:
            command_report.calibration(path, log, fit, cal=cal)
    return Calibration(log=log, model=fit.model, trajectory=trajectory_array(log.pose_times, fit.poses, fit.pose_std),
                       options=options, fit=fit, write_report=write_report, command=command)


def run(log_dir: str | Path, out: str | Path, method: str = "graph", sensor_degree: int = 3,
        effects: tuple = (), seed: int = 0, progress: Progress | None = None,
        regions: str | None = None, force: bool = False, command: str | None = None,
        max_sensor_degree: int = 6, sensor_basis: str = "auto") -> tuple[Log, Fit | dict]:
    """Load the bundle at ``log_dir``, calibrate it and write the run to ``out``; bad input raises LogError first.

    Returns the log and the method's :class:`Fit` (the model dict for the 1-D methods)."""
    checked_out(out, force, inputs=[log_dir])
    options = CalibrateOptions(method=method, sensor_degree=sensor_degree, effects=tuple(effects), seed=seed,
                               regions=regions, max_sensor_degree=max_sensor_degree, sensor_basis=sensor_basis)
    check_request(options)
    log = load(log_dir)
    cal = calibrate(log, options, progress=progress, command=command)
    if progress is not None:
        progress.stage("report", None)
    cal.save(out, force=force)
    return log, (cal.fit if cal.fit is not None else cal.model_json)
