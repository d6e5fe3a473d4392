"""The four calibration methods on each MRCLAM run-7 robot: do the EM methods agree with graph on real data?

Issue 20's bound: the command maps of ``graph-em`` and ``ekfs-em`` within 5 % of the velocity range of
``graph``'s. Per robot and method: the map difference from graph's, RMS over the commands the robot ran, as a
share of the range of graph's velocities over those commands (forward and turn), the position RMS against
Vicon, and the wall time (methods run one after another on one core).

    OPENBLAS_NUM_THREADS=1 python benchmarks/mrclam_methods.py [--robots 1 2 3 4 5] [--minutes M] [--methods graph-em]
    OPENBLAS_NUM_THREADS=1 python benchmarks/mrclam_methods.py --floor-seed 2 --minutes 4    # a simulated floor
    OPENBLAS_NUM_THREADS=1 python benchmarks/mrclam_methods.py --robots 3 --methods graph-em:inverse_distance

With ``--floor-seed`` the log is the simulator's continuous-command floor instead (no Vicon column). A method
written ``METHOD:BASIS`` calibrates with ``sensor_basis=BASIS`` (the EM methods keep the paper's cubic in d
unless told; graph chooses the curve's variable from the data).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import casm_graph as cg  # noqa: E402
from casm_graph.analysis import groundtruth  # noqa: E402
from casm_graph.io import mrclam  # noqa: E402

METHODS = ("graph", "graph-em", "ekfs-em-learned", "ekfs-em")


def one(data: Path, robot: int, minutes: float | None, floor_seed: int | None = None, methods=METHODS,
        step_heading: str = "auto") -> dict:
    if floor_seed is not None:
        log, _ = cg.simulate("floor", minutes=minutes or 4, seed=floor_seed)
    else:
        log, _ = mrclam.load_robot(data, robot)
        if minutes:
            log = log.window(log.t[0], log.t[0] + 60 * minutes)
    out = {}
    for m in methods:
        t = time.perf_counter()
        method, _, basis = m.partition(":")
        cal = cg.calibrate(log, method=method, sensor_basis=basis or "auto", step_heading=step_heading)
        v = cal.model.command.velocities(log.controls, log.dt)
        tr = cal.trajectory
        pos = float(np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)))
        seconds = time.perf_counter() - t
        if floor_seed is None and m == "graph":
            ref = groundtruth.truth_fit(log, cal.model.command)      # the same map form, the poses held at Vicon
        vicon = (groundtruth.map_errors(cal.model.command, ref, log.controls, log.dt) if floor_seed is None
                 else {"v": {"fraction": float("nan")}, "w": {"fraction": float("nan")}})
        out[m] = {"v": v, "position_rms": pos, "seconds": seconds,
                  "speed_vs_vicon": vicon["v"]["fraction"], "turn_vs_vicon": vicon["w"]["fraction"],
                  "v_coef": cal.model.command.v_coef.tolist(), "w_coef": cal.model.command.w_coef.tolist()}
    ref = out["graph"]["v"]
    span = np.ptp(ref, axis=0)
    for m in methods:
        d = np.sqrt(np.mean((out[m]["v"] - ref) ** 2, axis=0))
        out[m]["speed_vs_graph"] = float(d[0] / span[0])
        out[m]["turn_vs_graph"] = float(d[2] / span[2])
        del out[m]["v"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(mrclam.find_data()))
    ap.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--minutes", type=float)
    ap.add_argument("--floor-seed", type=int, help="a simulated floor of this seed instead of the robots")
    ap.add_argument("--methods", nargs="+", default=list(METHODS),
                    help="METHOD or METHOD:BASIS (graph always runs first, with the data's curve; the others are "
                         "compared with it)")
    ap.add_argument("--json")
    ap.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    a = ap.parse_args(argv)
    bad = [m for m in a.methods if m.partition(":")[0] not in METHODS]
    if bad:
        ap.error(f"unknown method(s) {bad}; known: {', '.join(METHODS)} "
                 "(optionally :distance or :inverse_distance)")
    rows = {}
    print("| log | method | speed / turn map vs graph, % of range | speed / turn map vs Vicon's, % | position RMS m | s |")
    print("|---|---|---:|---:|---:|---:|")
    for r in (["floor"] if a.floor_seed is not None else a.robots):
        rows[r] = one(Path(a.data), r, a.minutes, a.floor_seed, ["graph"] + [m for m in a.methods if m != "graph"],
                      a.step_heading)
        for m, e in rows[r].items():
            print(f"| {r} | {m} | {100 * e['speed_vs_graph']:.1f} / {100 * e['turn_vs_graph']:.1f} | "
                  f"{100 * e['speed_vs_vicon']:.1f} / {100 * e['turn_vs_vicon']:.1f} | "
                  f"{e['position_rms']:.3f} | {e['seconds']:.0f} |", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
