"""Range-only and bearing-only robots against range+bearing on the same trajectories (issue 22).

    OPENBLAS_NUM_THREADS=1 python benchmarks/one_channel.py [--seeds 5] [--minutes 10] [--json one_channel.json]
    OPENBLAS_NUM_THREADS=1 python benchmarks/one_channel.py --quick          # smoke run: 2 seeds, 6 minutes
    OPENBLAS_NUM_THREADS=1 python benchmarks/one_channel.py --uncertainty --modes both bearing range

For each seed s in 0..N-1 the floor simulator (``cg.simulate("floor", ...)``) writes one log per
sensor mode with the same seed, so the same trajectory, commands and landmarks: ``both`` (range and
bearing, forward camera), ``bearing`` (the same sightings without the range), ``range`` (a radio/UWB
like sensor that sees all around it, reading = distance) and ``range-tof`` (range-only with a
time-of-flight curve, reading = 0.1 m + 1.07 d, and 10 % non-line-of-sight readings carrying an extra
exponential error of mean 1 m). All use four landmarks and a larger ``max_range`` (default 15 m: the
whole 12 x 8 m floor) so a forward-looking camera sees enough of them. Each log is calibrated with the
public API, ``cg.calibrate(log, seed=s)``, and measured against the simulator's truth:

* traj m, heading rad: RMS position and (wrapped) heading error of ``cal.trajectory`` against
  ``log.truth`` at every pose time (world frame; the landmarks fix it, no alignment);
* speed map, turn map: the learned command map against the true one (velocity = command) over the
  commands in the log, ``cal.model.command.velocities(log.controls, log.dt)`` vs the command itself,
  as RMS(learned - command) / RMS(command) (a relative error; not per-sample, the turn command passes
  through zero);
* curve m: RMS over the visited distances (true distance of every sighting, from the truth poses) of
  the learned reading polynomial minus the true curve ``range_offset + range_scale d`` (bearing-only: none);
* reading sigma (m) and bearing sigma (rad), learned, beside the truth (none where the channel is not
  measured, ``cal.model.has(...)`` false); on ``range-tof`` the NLOS tail is not part of the true
  sigma (0.05 m), so the learned one there says how the tail was absorbed;
* seconds: wall time of ``cg.calibrate``;
* with ``--uncertainty``: ``cg.uncertainty(log, cal, seed=s)`` (emcee at its defaults) and whether each sampled
  sensor sigma's 90 % interval holds the simulator's, printed per mode after the medians.

One row per (mode, seed), then the median over seeds per mode, both as Markdown on stdout (progress on
stderr); ``--json PATH`` writes the options, rows and summary. A calibration that raises is recorded
with its error message and the run goes on. Every random choice comes from the seed (simulation and
calibration); runs are one process at a time.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import casm_graph as cg

MODES = {                       # mode -> floor simulator options beyond the common ones
    "both": {"sensor": "both"},
    "range": {"sensor": "range"},
    "bearing": {"sensor": "bearing"},
    "range-tof": {"sensor": "range", "range_scale": 1.07, "range_offset": 0.1, "nlos_fraction": 0.1, "nlos_scale": 1.0},
}
BAD_TRAJECTORY = 0.5            # m: a trajectory RMS above this is flagged in the tables
COLUMNS = [("traj_rms", "traj m", ".3f"), ("heading_rms", "heading rad", ".4f"), ("speed_rel", "speed map", ".2%"),
           ("turn_rel", "turn map", ".2%"), ("curve_rms", "curve m", ".4f"), ("reading_sigma", "reading sigma m", ".4f"),
           ("bearing_sigma", "bearing sigma rad", ".4f"), ("seconds", "seconds", ".1f")]


def wrap(a):
    return np.mod(np.asarray(a, float) + np.pi, 2 * np.pi) - np.pi


def rel_rms(learned: np.ndarray, true: np.ndarray) -> float:
    return float(np.sqrt(np.mean((learned - true) ** 2)) / np.sqrt(np.mean(true ** 2)))


def measure(log, truth: dict, cal) -> dict:
    """The errors of one calibration against the simulator's truth, as plain numbers (None: not measured)."""
    tr = cal.trajectory
    est = np.column_stack([tr["x"], tr["y"], tr["theta"]])
    true = log.truth[:, 1:]
    if est.shape != true.shape:
        raise ValueError(f"trajectory has {len(est)} poses, truth {len(true)}")
    traj = float(np.sqrt(np.mean(np.sum((est[:, :2] - true[:, :2]) ** 2, axis=1))))
    heading = float(np.sqrt(np.mean(wrap(est[:, 2] - true[:, 2]) ** 2)))
    m = cal.model
    c = np.asarray(log.controls, float)
    vel = m.command.velocities(c, log.dt)
    sm = truth["sensor_model"]
    out = {"traj_rms": traj, "heading_rms": heading, "speed_rel": rel_rms(vel[:, 0], c[:, 0]),
           "turn_rel": rel_rms(vel[:, 2], c[:, 1]), "curve_rms": None, "reading_sigma": None, "bearing_sigma": None,
           "true_reading_sigma": sm["range_sigma"] if "reading" in sm["channels"] else None,
           "true_bearing_sigma": sm["bearing_sigma"] if "bearing" in sm["channels"] else None,
           "command_lag": float(m.command.lag), "reading_poly": None,
           "converged": bool(m.fit.get("converged")), "iterations": m.fit.get("iterations")}
    if m.has("reading"):
        p = log.truth[log.obs_step, 1:3]
        d = np.hypot(*(log.landmark_xy[log.landmark_index] - p).T)
        curve = m.reading(d) - (sm["range_offset"] + sm["range_scale"] * d)
        out.update(curve_rms=float(np.sqrt(np.mean(curve ** 2))), reading_sigma=float(m.reading_sigma),
                   reading_poly=[float(x) for x in m.reading_poly])
    if m.has("bearing"):
        out["bearing_sigma"] = float(m.bearing_sigma)
    return out


def covered(log, truth: dict, cal, seed: int) -> dict:
    """Each sampled sensor sigma's 90 % interval and whether it holds the simulator's sigma."""
    sm = truth["sensor_model"]
    true = {"reading_sigma": sm["range_sigma"], "bearing_sigma": sm["bearing_sigma"]}
    post = cg.uncertainty(log, cal, seed=seed)
    return {n: {"ci90": post.intervals[n]["ci90"], "truth": t,
                "inside": bool(post.intervals[n]["ci90"][0] <= t <= post.intervals[n]["ci90"][1])}
            for n, t in true.items() if n in post.intervals}


def trial(mode: str, seed: int, minutes: float, common: dict, uncertainty: bool = False) -> dict:
    row = {"mode": mode, "seed": seed, "error": None}
    log, truth = cg.simulate("floor", minutes=minutes, seed=seed, **common, **MODES[mode])
    row["sightings"] = int(len(log.obs_t))
    t0 = time.perf_counter()
    try:
        cal = cg.calibrate(log, seed=seed)
    except Exception as e:          # recorded in the row; the benchmark goes on
        row.update(seconds=time.perf_counter() - t0, error=f"{type(e).__name__}: {e}".splitlines()[0])
        return row
    row["seconds"] = time.perf_counter() - t0
    try:
        row.update(measure(log, truth, cal))
        if uncertainty:
            row["coverage"] = covered(log, truth, cal, seed)
    except Exception as e:
        row["error"] = f"measuring: {type(e).__name__}: {e}".splitlines()[0]
    return row


def cell(v, spec: str) -> str:
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def sigma_cell(r: dict, key: str) -> str:
    learned = cell(r.get(key), ".4f")
    true = r.get("true_" + key)
    return learned if true is None else f"{learned} ({true:g})"


def print_row(r: dict) -> None:
    if r["error"]:
        print(f"| {r['mode']} | {r['seed']} | {r['sightings']} | " + " | ".join("" for _ in COLUMNS[:-1])
              + f" | {r['seconds']:.1f} | error: {r['error']} |", flush=True)
        return
    vals = [sigma_cell(r, k) if k in ("reading_sigma", "bearing_sigma") else cell(r[k], f) for k, _, f in COLUMNS]
    notes = [] if r["converged"] else ["not converged"]
    if r["traj_rms"] > BAD_TRAJECTORY:
        notes.append(f"traj > {BAD_TRAJECTORY} m")
    print(f"| {r['mode']} | {r['seed']} | {r['sightings']} | " + " | ".join(vals) + f" | {', '.join(notes) or 'ok'} |",
          flush=True)


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for mode in MODES:
        sel = [r for r in rows if r["mode"] == mode]
        if not sel:
            continue
        ok = [r for r in sel if not r["error"]]
        s = {"mode": mode, "seeds": len(sel), "failed": len(sel) - len(ok),
             "bad_trajectory": sum(r["traj_rms"] > BAD_TRAJECTORY for r in ok),
             "worst_traj_rms": max((r["traj_rms"] for r in ok), default=None),
             "true_reading_sigma": next((r["true_reading_sigma"] for r in ok), None),
             "true_bearing_sigma": next((r["true_bearing_sigma"] for r in ok), None),
             "sightings": float(np.median([r["sightings"] for r in sel]))}
        for k, _, _ in COLUMNS:
            vals = [r[k] for r in ok if r.get(k) is not None]
            s[k] = float(np.median(vals)) if vals else None
        out.append(s)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (default 5)")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--landmarks", type=int, default=4)
    ap.add_argument("--max-range", type=float, default=15.0, help="m (the floor simulator's default is 5)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 seeds, 6 minutes")
    ap.add_argument("--json", default=None, help="also write the options, rows and summary here")
    ap.add_argument("--uncertainty", action="store_true", help="also run cg.uncertainty and report interval coverage")
    a = ap.parse_args(argv)
    if a.quick:
        a.seeds, a.minutes = 2, 6.0
    common = {"n_landmarks": a.landmarks, "max_range": a.max_range}
    opts = {"protocol": "floor", "minutes": a.minutes, "seeds": list(range(a.seeds)), **common,
            "modes": {m: MODES[m] for m in a.modes}, "calibrate": "cg.calibrate(log, seed=seed)"}
    print("floor simulator: " + ", ".join(f"{k}={v}" for k, v in common.items()) + f", minutes={a.minutes:g}, "
          f"seeds 0..{a.seeds - 1}; other options at FloorConfig defaults; per mode: "
          + "; ".join(f"{m}: " + ", ".join(f"{k}={v}" for k, v in MODES[m].items()) for m in a.modes) + "\n")
    print("| mode | seed | sightings | " + " | ".join(h for _, h, _ in COLUMNS) + " | status |")
    print("|---|---:|---:|" + "---:|" * len(COLUMNS) + "---|")
    t_all = time.perf_counter()
    rows = []
    for seed in range(a.seeds):
        for mode in a.modes:
            print(f"seed {seed} {mode}: simulating and calibrating ...", file=sys.stderr, flush=True)
            r = trial(mode, seed, a.minutes, common, a.uncertainty)
            rows.append(r)
            print_row(r)
            print(f"seed {seed} {mode}: {r['seconds']:.1f} s" + (f", error {r['error']}" if r["error"] else
                  f", traj {r['traj_rms']:.3f} m"), file=sys.stderr, flush=True)
    wall = time.perf_counter() - t_all
    summary = summarise(rows)
    print(f"\nMedian over {a.seeds} seeds (sigma columns: learned (true); – where the channel is not measured):\n")
    print("| mode | seeds ok | " + " | ".join(h for _, h, _ in COLUMNS) + f" | worst traj m | traj > {BAD_TRAJECTORY} m |")
    print("|---|---:|" + "---:|" * len(COLUMNS) + "---:|---:|")
    for s in summary:
        vals = [sigma_cell(s, k) if k in ("reading_sigma", "bearing_sigma") else cell(s[k], f) for k, _, f in COLUMNS]
        print(f"| {s['mode']} | {s['seeds'] - s['failed']}/{s['seeds']} | " + " | ".join(vals)
              + f" | {cell(s['worst_traj_rms'], '.3f')} | {s['bad_trajectory']} |")
    if a.uncertainty:
        print("\n90 % intervals of the sensor sigmas holding the simulator's (seeds where the interval missed):\n")
        print("| mode | reading sigma | bearing sigma |")
        print("|---|---|---|")
        for mode in a.modes:
            cov = [r for r in rows if r["mode"] == mode and r.get("coverage")]
            cells = []
            for n in ("reading_sigma", "bearing_sigma"):
                got = [(r["seed"], r["coverage"][n]) for r in cov if n in r["coverage"]]
                miss = [f"{sd}: [{c['ci90'][0]:.4f}, {c['ci90'][1]:.4f}]" for sd, c in got if not c["inside"]]
                cells.append("–" if not got else f"{sum(c['inside'] for _, c in got)} of {len(got)}"
                             + (f" (seed {'; '.join(miss)})" if miss else ""))
            print(f"| {mode} | " + " | ".join(cells) + " |")
    print(f"\n(wall time {wall:.0f} s)")
    if a.json:
        Path(a.json).write_text(json.dumps({"options": opts, "wall_seconds": wall, "rows": rows, "summary": summary},
                                           indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
