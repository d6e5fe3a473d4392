"""Calibration: a log and options in, a :class:`~casm_graph.fit.calibration.Calibration` out (in memory).

``calibrate`` hands the log to the part of its kind of action model
(:mod:`casm_graph.fit.methods.kinds`), which starts, fits it by the method asked for and adds the requested
effects, and returns the result; ``Calibration.save`` writes the run directory. ``run`` is the two together, as
``casm-graph calibrate`` does them.
"""
from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from casm_graph.baselines import scasm_run
from casm_graph.fit.calibration import CalibrateOptions, Calibration, read_truth_model, trajectory_array
from casm_graph.fit.frame import in_map_frame
from casm_graph.fit.methods import METHODS, Fit, Progress
from casm_graph.fit.methods.kinds import kind
from casm_graph.fit.result import LIKELIHOOD_DROP
from casm_graph.io.identifiability import check_identifiable
from casm_graph.io.log import Log, LogError, load
from casm_graph.io.output import checked_out
from casm_graph.models.command_model import STEP_HEADINGS
from casm_graph.models.effects import get as get_effect
from casm_graph.models.effects import unphysical
from casm_graph.report import pages as report
from factors.reading import BASES


SCASM_METHODS = scasm_run.METHODS             # 1-D logs: their own model kinds and report
LOOSE_POSITION = 0.05       # one channel: a median posterior position std beyond this share of the field is warned of
LOOSE_HEADING = 0.2         # rad: a median posterior heading std beyond this is warned of, whatever the channels
LOOSE_POSITION_WARNING = ("with one sensor channel this log places the robot only to about {:.2g} m (median posterior "
                    "position std, {:.0%} of the landmarks' extent): the model rests on little; both channels, more "
                    "precise sightings or a longer log pin it down")
LOOSE_HEADING_WARNING = ("this log leaves the robot's heading loose: median posterior heading std {:.2f} rad ({:.0f} "
                   "degrees), so the turn map and the trajectory rest on little and the fit may sit in a wrong basin "
                   "(the motion noise it needs, turn {:.3g} rad per step, says how little the commands explain); "
                   "bearings, more precise readings or a longer log pin it down")


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
    if options.cross_terms not in (True, False, "auto"):
        raise LogError(f"cross_terms must be True, False or 'auto' (got {options.cross_terms!r})")
    if options.step_heading not in ("auto", *STEP_HEADINGS):
        raise LogError(f"--step-heading must be one of auto, {', '.join(STEP_HEADINGS)} "
                       f"(got {options.step_heading!r})")
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
    part = kind(log.action_model_kind)
    part.check(log, options, classes)
    heading = part.step_heading if options.step_heading == "auto" else options.step_heading
    start = part.start_model(log, options.sensor_degree, start_basis(options), cross=options.cross_terms is True,
                             step_heading=heading)
    fit = in_map_frame(log, part.calibrate(log, start, options, classes, progress), classes)
    warn_if_worse(fit, classes)
    warn_if_unphysical(log, fit, classes)
    warn_if_loose(log, fit)
    return Calibration(log=log, model=fit.model, trajectory=trajectory_array(log.pose_times, fit.poses, fit.pose_std),
                       options=options, fit=fit,
                       write_report=lambda path, cal: report.calibration(path, log, fit, cal,
                                                                         truth=read_truth_model(log.source)),
                       command=command)


def warn_if_worse(fit: Fit, classes: list) -> None:
    """A RuntimeWarning when adding least-squares effects left the log-likelihood below the fit without them: the
    model with them holds the one without (each effect at its neutral value), so their fit stopped in a local
    optimum (an omni world's carpet patch: 36,783 without it, 36,477 with its slow-down at -4.3). Where the fit
    without them was refitted as the effects' was (``refit_log_likelihood``: an action table's base holds its own
    noise levels), that is the one compared, and a base that only its own noise levels keep above both is said.
    An action table's effect fit whose last round fell below its start or an earlier round returns that state
    (``kept_round``: the notebook's glare at 0.2, whose rounds fall from -14,425 to -15,600): said first. Noise
    effects change what the likelihood counts (a mixture scores every sighting) and are not compared."""
    base = fit.notes.get("base_log_likelihood")
    kept = fit.notes.get("kept_round")
    if kept is not None and classes:
        names = ", ".join(c.name for c in classes)
        where = ("its start (the base's model and poses, the effects at their start values)" if kept == 0 else
                 f"its round {kept}")
        warnings.warn(f"adding {names}: the fit's last round left the log-likelihood at "
                      f"{fit.notes['last_log_likelihood']:,.1f}, below {fit.log_likelihood:,.1f} at {where}, which "
                      f"is kept: least squares from the base's poses fall into a worse optimum, so the base misfits "
                      f"this log in a way {names} does not mend (check the base's report, and `diagnose`)",
                      RuntimeWarning, stacklevel=3)
        return
    if base is None or not classes or any(c.noise_only for c in classes) or fit.log_likelihood >= base - LIKELIHOOD_DROP:
        return
    names = ", ".join(c.name for c in classes)
    refit = fit.notes.get("refit_log_likelihood")
    if refit is not None and fit.log_likelihood >= refit - LIKELIHOOD_DROP:
        warnings.warn(f"adding {names} left the log-likelihood at {fit.log_likelihood:,.1f}, below the base's "
                      f"{base:,.1f} with its own noise levels, but above the {refit:,.1f} the base reaches refitted "
                      f"as the effects were (every level free on the step graph): the base misfits this log so "
                      f"badly that the two figures part; {names} is not what fails (check the base's report, and "
                      f"`diagnose`)", RuntimeWarning, stacklevel=3)
        return
    below = base if refit is None else refit
    warnings.warn(f"adding {names} lowered the log-likelihood from {below:,.1f} to {fit.log_likelihood:,.1f}: "
                  f"the fit stopped in a local optimum from its start, and the model without it explains the "
                  f"log better (`diagnose` says which form fits; another --seed starts the base elsewhere)",
                  RuntimeWarning, stacklevel=3)


def warn_if_loose(log: Log, fit: Fit) -> None:
    """A RuntimeWarning when the posterior leaves the robot loose, for every kind of action model: its position
    with one sensor channel (the Aibo's 0.5-rad bearings alone: about 0.5 m), its heading whatever the channels (a
    radio's ranges in dB, 2-4 dB of noise: the wheel world's seed 1 ended 45 degrees off with a heading std of 0.57
    rad, where a log that pins the robot down has 0.005-0.07). Nothing to say without marginals."""
    std = np.asarray(fit.pose_std, float)
    if std.ndim != 2 or not np.isfinite(std).all(axis=1).any():
        return
    std = std[np.isfinite(std).all(axis=1)]
    spread = float(np.median(np.hypot(std[:, 0], std[:, 1])))
    extent = float(np.ptp(log.landmark_xy, axis=0).max())
    if len(fit.model.channels) == 1 and spread > LOOSE_POSITION * extent:
        warnings.warn(LOOSE_POSITION_WARNING.format(spread, spread / extent), RuntimeWarning, stacklevel=3)
    heading = float(np.median(std[:, 2]))
    if heading > LOOSE_HEADING:
        warnings.warn(LOOSE_HEADING_WARNING.format(heading, np.degrees(heading), float(fit.model.motion_noise[2])),
                      RuntimeWarning, stacklevel=3)


def warn_if_unphysical(log: Log, fit: Fit, classes: list) -> None:
    """A RuntimeWarning for each added effect whose fitted parameters cannot happen (:meth:`Effect.implausible`):
    the effect's form was bent around structure of another kind."""
    for cls in classes:
        entry = fit.model.effects.get(cls.name)
        why = None if not entry else unphysical(cls, entry, log)
        if why:
            warnings.warn(f"{cls.name}'s fit is not physical: {why}; the log's structure is of another kind "
                          f"(`diagnose` without it says what else explains it)", RuntimeWarning, stacklevel=3)


def run(log_dir: str | Path, out: str | Path, method: str = "graph", sensor_degree: int = 3,
        effects: tuple = (), seed: int = 0, progress: Progress | None = None,
        regions: str | None = None, force: bool = False, command: str | None = None,
        max_sensor_degree: int = 6, sensor_basis: str = "auto", cross_terms: bool | str = "auto",
        step_heading: str = "auto") -> tuple[Log, Fit | dict]:
    """Load the bundle at ``log_dir``, calibrate it and write the run to ``out``; bad input raises LogError first.

    Returns the log and the method's :class:`Fit` (the model dict for the 1-D methods)."""
    checked_out(out, force, inputs=[log_dir])
    options = CalibrateOptions(method=method, sensor_degree=sensor_degree, effects=tuple(effects), seed=seed,
                               regions=regions, max_sensor_degree=max_sensor_degree, sensor_basis=sensor_basis,
                               cross_terms=cross_terms, step_heading=step_heading)
    check_request(options)
    log = load(log_dir)
    cal = calibrate(log, options, progress=progress, command=command)
    if progress is not None:
        progress.stage("report", None)
    cal.save(out, force=force)
    return log, (cal.fit if cal.fit is not None else cal.model_json)
