"""Omnidirectional robots (``vx, vy, w`` commands) on the omni world, ``tests/worlds/omni_world.py``.

That generator was written apart from casm_graph (by a helper that did not read it): a walker whose true
velocities are gains, offsets and a quadratic forward term of its commands, slipping as an Ornstein-Uhlenbeck
process in a 200 Hz integration, seen by a camera whose apparent size a / (d + b) + c is no polynomial in d.
Each world is calibrated by every method; the maps are compared with the world's over the commands run (RMS,
share of each map's range), the sensor curve over 0.4-6 m, the trajectory with the truth.

    OPENBLAS_NUM_THREADS=1 python benchmarks/omni.py --seeds 0 1 2 3 4 5 --minutes 4 \
        [--methods graph graph-em graph-em:inverse_distance ekfs-em]

A method written ``METHOD:BASIS`` calibrates with ``sensor_basis=BASIS`` (the EM methods keep the paper's cubic in
d unless told: only ``graph`` lets the data choose the curve's variable).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                    # noqa: E402
from tests.worlds import omni_world        # noqa: E402


def errors(log, truth: dict, cal) -> dict:
    """Map errors per axis (share of range), sensor-curve RMS over the camera's range (px), position RMS (m)."""
    true = omni_world.true_velocities(truth, log.controls)
    learned = cal.model.command.velocities(log.controls)
    maps = np.sqrt(np.mean((learned - true) ** 2, axis=0)) / np.ptp(true, axis=0)
    s = truth["sensor"]
    d = np.linspace(s["range_min"], s["range_max"], 200)
    curve = float(np.sqrt(np.mean((cal.model.reading(d) - (s["a"] / (d + s["b"]) + s["c"])) ** 2)))
    tr = cal.trajectory
    pos = float(np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)))
    return {"maps": maps, "curve": curve, "position": pos, "basis": cal.model.reading_basis,
            "degree": len(cal.model.reading_poly) - 1}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--minutes", type=float, default=4.0)
    ap.add_argument("--methods", nargs="+", default=["graph", "graph-em", "graph-em:inverse_distance", "ekfs-em"])
    ap.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    args = ap.parse_args()
    print("| method | seed | forward / sideways / turn map, % of range | sensor curve | curve RMS px | position RMS m |")
    print("|---|---|---|---|---:|---:|")
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as w:
            truth = omni_world.generate(Path(w) / "log", minutes=args.minutes, seed=seed)
            log = cg.load_log(Path(w) / "log")
            for spec in args.methods:
                method, _, basis = spec.partition(":")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    e = errors(log, truth, cg.calibrate(log, method=method, seed=seed, sensor_basis=basis or "auto",
                                                        step_heading=args.step_heading))
                print(f"| {spec} | {seed} | {' / '.join(f'{100 * x:.1f}' for x in e['maps'])} | degree "
                      f"{e['degree']} in {'1/d' if e['basis'] == 'inverse_distance' else 'd'} | {e['curve']:.2f} | "
                      f"{e['position']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
