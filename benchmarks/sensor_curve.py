"""The sensor curve's variable on the independent world's camera (an apparent size a / (d + b) + c).

Each seed's four-minute action-table log is calibrated with the curve in d (``--sensor-basis distance``, the
degree raised by the data) and with the default (``auto``: 1/d competing when the fit in d misses near the
landmarks); errors against the world's truth as tests/test_independent_world.py computes them.

    OPENBLAS_NUM_THREADS=1 python benchmarks/sensor_curve.py --seeds 0 1 2
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                                    # noqa: E402
from casm_graph.analysis.groundtruth import position_rms  # noqa: E402
from tests.worlds.independent_world import generate        # noqa: E402


def errors(cal, log, truth) -> dict:
    """Table RMS (vx, vy, w), sensor-curve RMS over the distances seen, position RMS."""
    true = np.array([truth["realized_velocities"][str(int(a))] for a in cal.model.action_ids])
    table = np.sqrt(np.mean((cal.model.velocities - true) ** 2, axis=0))
    tr = cal.trajectory
    seen = np.hypot(*(log.landmark_xy[log.landmark_index] - np.column_stack([tr["x"], tr["y"]])[log.obs_step]).T)
    lo, hi = np.percentile(seen, [2, 98])
    d, r = np.array(truth["sensor_curve"]["samples"]).T
    sel = (d >= lo) & (d <= hi)
    return {"table": table, "curve": float(np.sqrt(np.mean((cal.model.reading(d[sel]) - r[sel]) ** 2))),
            "position": position_rms(np.column_stack([tr["x"], tr["y"]]), log.truth)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--minutes", type=float, default=4.0)
    args = ap.parse_args()
    print("| seed | --sensor-basis | curve fitted | table RMS vx / vy mm/s, w rad/s | curve RMS px | position RMS m |")
    print("|---|---|---|---|---|---|")
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as w:
            truth = generate(Path(w) / "log", kind="table", minutes=args.minutes, seed=seed)
            log = cg.load_log(Path(w) / "log")
            for basis in ("distance", "auto"):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    cal = cg.calibrate(log, seed=seed, sensor_basis=basis)
                e, sd = errors(cal, log, truth), cal.model.fit["sensor_degree"]
                print(f"| {seed} | {basis} | degree {sd['fitted']} in {sd['basis']} | {1000 * e['table'][0]:.1f} / "
                      f"{1000 * e['table'][1]:.1f}, {e['table'][2]:.3f} | {e['curve']:.2f} | {e['position']:.3f} |",
                      flush=True)


if __name__ == "__main__":
    main()
