"""Can this log pin the model down at all? Checked before any computation, one clear line if not.

A log that :func:`casm_graph.io.log.load` accepts is well formed, but it may still be unable to
determine the model asked for: a channel missing altogether, too few sightings or command steps
for the unknowns, all landmarks at one place (then only the product of scale and sensor curve is
seen, never the curve), or runs of one action too short for the start's knots. Such logs are
rejected here with a :class:`LogError` naming file and column, before the fit could crash or
write NaN.
"""
from __future__ import annotations

import numpy as np

from casm_graph.io.log import Log, LogError

MIN_SIGHTINGS = 10          # sightings in the whole log
MIN_BEARINGS = 10           # sightings with a bearing
MIN_STEPS = 15              # command steps: the start places the robot on knots 5 steps apart, scores on 15
MIN_RUN_STEPS = 15          # steps of an action's longest run: the start needs three of its knots (5 steps apart)
MIN_SPREAD = 0.01           # m: sighted landmarks closer together than this stand at one place
NOISE_LEVELS = 5            # reading sigma, bearing sigma, motion noise (3)
START_POSE = 3
ONE_D_METHODS = ("scasm", "scasm-graph")   # 1-D logs: their own model and checks (scasm_run)


def _min_readings(sensor_degree: int) -> int:
    return max(MIN_SIGHTINGS, 2 * (sensor_degree + 1))


def check_identifiable(log: Log, sensor_degree: int = 3, method: str = "graph") -> None:
    """Raise :class:`LogError` (one line) when ``log`` cannot determine the model ``calibrate`` would fit.

    ``sensor_degree`` is the degree of the reading polynomial asked for; ``method`` the calibration
    method (the 1-D methods ``scasm``/``scasm-graph`` have their own model and are not checked here).
    """
    if method in ONE_D_METHODS:
        return
    has_r = ~np.isnan(np.asarray(log.obs_reading, float))
    has_b = ~np.isnan(np.asarray(log.obs_bearing, float))
    n_obs, n_r, n_b = len(log.obs_t), int(has_r.sum()), int(has_b.sum())

    # a channel missing altogether: range-only or bearing-only sensors (an action table with bearings only
    # needs actions.csv for its start)
    if n_r == 0 and n_b == 0:
        raise LogError("observations.csv: no sighting has a reading or a bearing")
    one = "reading" if n_b == 0 else "bearing" if n_r == 0 else None
    if one == "bearing" and log.action is not None and not log.attempted:
        raise LogError("observations.csv, column 'reading': every cell is empty (a bearing-only log); an action-table "
                       "log with bearings only needs actions.csv (each action's attempted velocity) for its start")

    # too short for the model asked
    if log.steps < MIN_STEPS:
        kind = ("" if log.action is not None else
                f" of continuous commands '{','.join(log.control_names)}' (an action-table log has an 'action' column)")
        raise LogError(f"commands.csv: only {log.steps} command step(s){kind}; calibrating needs at least "
                       f"{MIN_STEPS} (the log is too short)")
    if n_obs < MIN_SIGHTINGS:
        raise LogError(f"observations.csv: only {n_obs} sighting(s) in the whole log; calibrating needs at least "
                       f"{MIN_SIGHTINGS}")
    need_r = _min_readings(sensor_degree)
    if one == "bearing":
        need_r = 0           # no sensor curve to fit: the model records the reading channel as absent
    if 0 < n_r < need_r or (one is None and n_r < need_r):
        raise LogError(f"observations.csv, column 'reading': only {n_r} sighting(s) with a reading; a degree-"
                       f"{sensor_degree} sensor polynomial needs at least {need_r}")
    if n_b < MIN_BEARINGS and one != "reading":
        raise LogError(f"observations.csv, column 'bearing': only {n_b} sighting(s) with a bearing; calibrating "
                       f"needs at least {MIN_BEARINGS}")
    readings = np.unique(np.asarray(log.obs_reading, float)[has_r])
    if n_r and len(readings) < sensor_degree + 1:
        raise LogError(f"observations.csv, column 'reading': only {len(readings)} distinct value(s) "
                       f"({', '.join(f'{r:g}' for r in readings[:5])}); a degree-{sensor_degree} sensor polynomial "
                       f"needs at least {sensor_degree + 1} (a constant reading carries no distance)")
    bearings = np.unique(np.asarray(log.obs_bearing, float)[has_b])
    if n_b and len(bearings) < 2:
        raise LogError(f"observations.csv, column 'bearing': every bearing is {bearings[0]:g} rad; a constant "
                       f"bearing carries no information about the heading (the fit is not identifiable)")
    if log.action is not None:
        n_motion = 3 * len(np.unique(log.action))
        what = f"3 velocities for each of {n_motion // 3} action(s)"
    else:
        n_motion = 5                        # the command map's default degrees: v 2, w 1
        what = "5 command-map coefficients"
    unknowns = n_motion + sensor_degree + 1 + NOISE_LEVELS + START_POSE
    unknowns -= (sensor_degree + 2) * (n_r == 0) + (n_b == 0)
    if n_r + n_b < unknowns:
        raise LogError(f"observations.csv: {n_r} readings and {n_b} bearings cannot determine {unknowns} unknowns "
                       f"({what}, {sensor_degree + 1} sensor coefficients, {NOISE_LEVELS} noise levels, the "
                       f"start pose); the log is too short for this model")

    # an action whose runs are all too short for the start to fit its velocity
    if log.action is not None:
        a = np.asarray(log.action)
        start = np.concatenate([[0], np.flatnonzero(np.diff(a) != 0) + 1])
        length = np.diff(np.append(start, len(a)))
        for act in np.unique(a):
            mine = np.flatnonzero(a[start] == act)
            best = mine[np.argmax(length[mine])]
            if length[best] < MIN_RUN_STEPS:
                r0, r1 = log.file_row(start[best]), log.file_row(start[best] + length[best] - 1)
                raise LogError(f"commands.csv, row {r0}, column 'action': action {act} runs for only {length[best]} "
                               f"step(s) at most (rows {r0}-{r1}); the start fits each action's velocity on a run "
                               f"of at least {MIN_RUN_STEPS} command steps (three of its knots), so every action "
                               f"needs one such run (shorter runs of it elsewhere are fine)")

    # all sighted landmarks at one place: the sensor curve cannot be told from the scale (with bearings
    # only, the robot's distance from them is not seen at all)
    what = "reading" if n_r else "bearing"
    lm_ids = np.asarray(log.landmark_ids)
    order = np.argsort(lm_ids)
    rows = order[np.searchsorted(lm_ids[order], np.asarray(log.obs_landmark)[has_r if n_r else has_b])]
    xy = np.asarray(log.landmark_xy, float)[np.unique(rows)]
    spread = float(np.max(np.ptp(xy, axis=0))) if len(xy) else 0.0
    if spread < MIN_SPREAD:
        where = f"({xy[0, 0]:g}, {xy[0, 1]:g})"
        which = (f"the only landmark sighted with a {what} (id {lm_ids[rows[0]]}) stands at {where}"
                 if len(xy) == 1 else f"all {len(xy)} landmarks sighted with a {what} stand at {where} "
                                      f"(within {100 * MIN_SPREAD:g} cm)")
        lost = "the sensor polynomial" if n_r else "the robot's distance from it"
        raise LogError(f"landmarks.csv, columns 'x','y': {which}; with no second place to measure from, "
                       f"{lost} cannot be identified (coincident landmarks)")
