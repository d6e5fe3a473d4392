"""Bad-data trials: a simulated log with wild readings, swapped landmark ids or false detections, calibrated
from its bundle on disk and scored against its truth (benchmarks/robustness.py and tests/test_robustness.py).

Cases: ``clean``; ``wildN``: N readings multiplied by 10,000; ``swap2``: 2 % of the sightings given another
landmark's id; ``false20``: a log simulated with 20 % false detections, calibrated as is, and
``false20+fx`` with the ``false_detections`` effect.
"""
from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from casm_graph.io.log import Log
from casm_graph.io.log import load as load_log
from casm_graph.pipeline.calibrate import calibrate
from casm_graph.pipeline.hidden_effect import model_error
from casm_graph.sim.protocols import simulate, write_log

CASES = ("clean", "wild1", "wild5", "swap2", "false20", "false20+fx")


def corrupt(log: Log, case: str, rng: np.random.Generator) -> Log:
    """The clean ``log`` with the case's bad data put in (false detections come from the simulator instead)."""
    if case.startswith("wild"):
        n = int(case[4:])
        i = rng.choice(np.flatnonzero(np.isfinite(log.obs_reading)), size=n, replace=False)
        r = log.obs_reading.copy()
        r[i] *= 10_000.0
        return replace(log, obs_reading=r)
    if case == "swap2":
        i = rng.choice(len(log.obs_t), size=int(0.02 * len(log.obs_t)), replace=False)
        lm = log.obs_landmark.copy()
        ids = log.landmark_ids
        lm[i] = [rng.choice(ids[ids != k]) for k in lm[i]]
        return replace(log, obs_landmark=lm)
    return log


def trial(case: str, seed: int, minutes: float) -> dict:
    """One case on one seed: the table and sensor-curve errors against the truth, or the failure."""
    effects = {"false_detections": 0.2} if case.startswith("false20") else {}
    log, truth = simulate("aibo", minutes=minutes, seed=seed, effects=effects)
    log = corrupt(log, case, np.random.default_rng([seed, 99]))
    with tempfile.TemporaryDirectory() as d:       # through the bundle on disk, as a user's log arrives
        write_log(log, Path(d) / "log", truth)
        log = load_log(Path(d) / "log")
        try:
            cal = calibrate(log, effects=["false_detections"] if case.endswith("+fx") else [], seed=seed)
        except Exception as exc:        # the figure to report is the failure itself (a crash is a result here)
            return {"case": case, "seed": seed, "status": f"{type(exc).__name__}: {str(exc).splitlines()[0][:60]}"}
    e = model_error(cal.model, truth)
    return {"case": case, "seed": seed, "status": "ok", "vx": 1000 * e["vx"], "vy": 1000 * e["vy"], "w": e["w"],
            "curve": e["curve"], "reading_sigma": cal.model.reading_sigma,
            "converged": bool(cal.model.fit.get("converged"))}
