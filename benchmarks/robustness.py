"""Bad data against the table's error: wild readings, swapped landmark ids, false detections.

    OPENBLAS_NUM_THREADS=1 python benchmarks/robustness.py [--minutes 6] [--seeds 0 1] [--cases clean wild1 ...]

Per seed: a simulated Aibo log (clean), then the same log with one reading multiplied by 10,000
(``wild1``), five such readings (``wild5``), 2 % of the sightings given another landmark's id
(``swap2``), and a log simulated with 20 % false detections, calibrated without and with the
``false_detections`` effect (``false20``, ``false20+fx``). Prints each case's velocity-table RMS
error against the truth (mm/s, mm/s, rad/s), the sensor curve's error (px), the reading sigma and
the exit status, beside the clean log's, and the ratio to clean that the targets are stated in.
"""
from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

import casm_graph as cg

CASES = ("clean", "wild1", "wild5", "swap2", "false20", "false20+fx")


def corrupt(log: cg.Log, case: str, rng: np.random.Generator) -> cg.Log:
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


def run(case: str, seed: int, minutes: float) -> dict:
    effects = {"false_detections": 0.2} if case.startswith("false20") else {}
    log, truth = cg.simulate("aibo", minutes=minutes, seed=seed, effects=effects)
    log = corrupt(log, case, np.random.default_rng([seed, 99]))
    with tempfile.TemporaryDirectory() as d:       # through the bundle on disk, as a user's log arrives
        cg.write_log(log, Path(d) / "log", truth)
        log = cg.load_log(Path(d) / "log")
        try:
            cal = cg.calibrate(log, effects=["false_detections"] if case.endswith("+fx") else [], seed=seed)
        except Exception as exc:        # the figure to report is the failure itself
            return {"case": case, "seed": seed, "status": f"{type(exc).__name__}: {str(exc).splitlines()[0][:60]}"}
    e = cg.model_error(cal.model, truth)
    return {"case": case, "seed": seed, "status": "ok", "vx": 1000 * e["vx"], "vy": 1000 * e["vy"], "w": e["w"],
            "curve": e["curve"], "reading_sigma": cal.model.reading_sigma,
            "converged": bool(cal.model.fit.get("converged"))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    a = ap.parse_args()
    rows = [run(c, s, a.minutes) for s in a.seeds for c in a.cases]
    clean = {r["seed"]: r for r in rows if r["case"] == "clean" and r["status"] == "ok"}
    print("| case | seed | vx mm/s | vy mm/s | w rad/s | curve px | reading sigma | vx, vy / clean | status |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["status"] != "ok":
            print(f"| {r['case']} | {r['seed']} | | | | | | | {r['status']} |")
            continue
        c = clean.get(r["seed"])
        ratio = f"{r['vx'] / c['vx']:.2f}, {r['vy'] / c['vy']:.2f}" if c else ""
        print(f"| {r['case']} | {r['seed']} | {r['vx']:.1f} | {r['vy']:.1f} | {r['w']:.4f} | {r['curve']:.2f} | "
              f"{r['reading_sigma']:.3g} | {ratio} | {'converged' if r['converged'] else 'not converged'} |")


if __name__ == "__main__":
    main()
