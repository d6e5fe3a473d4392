"""Action-table robots with one sensor channel, on the independent world: model and trajectory from the log alone.

The world's table robot carrying a ranging radio (affine time-of-flight curve, 5 cm noise, landmarks all
around, no bearings). One rotation is free without bearings (every heading and every body velocity turned
together), so headings and body velocities are compared after the one rotation that best aligns the
headings with the truth; its size is printed too (the start fixes it along actions.csv's attempted
directions). Compared against the world's realised per-action velocities.

With ``--sensor bearing`` the world's camera robot with its blob sizes dropped (bearings only; no curve, no
free rotation: the bearings fix the headings).

    OPENBLAS_NUM_THREADS=1 python benchmarks/range_only_table.py --seeds 0 1 2 3 4 --minutes 8 [--sensor bearing]
"""
import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import casm_graph as cg  # noqa: E402
from casm_graph.io.log import wrap  # noqa: E402
from tests.worlds.independent_world import generate  # noqa: E402


def one(seed: int, minutes: float, sensor: str = "range") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "log"
        generate(d, kind="table", minutes=minutes, seed=seed, sensor=sensor)
        truth = json.loads((d / "world_truth.json").read_text())
        log = cg.load_log(d)
        t = time.perf_counter()
        cal = cg.calibrate(log)
        seconds = time.perf_counter() - t
    tr = cal.trajectory
    dh = wrap(tr["theta"] - log.truth[:, 3])
    turn = float(np.angle(np.mean(np.exp(1j * dh))))             # the free rotation
    tv = np.array([truth["realized_velocities"][str(int(a))] for a in cal.model.action_ids])
    v = cal.model.velocities
    c, s = np.cos(turn), np.sin(turn)
    aligned = np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]])
    dist = np.linspace(*cal.model.distance_range, 50)
    curve = truth["sensor_curve"]
    true_r = curve["s"] * dist + curve["o"] if curve["kind"] == "affine" else np.full_like(dist, np.nan)
    sigma = cal.model.reading_sigma if sensor == "range" else cal.model.bearing_sigma
    return {"seed": seed, "position_rms": float(np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2
                                                                + (tr["y"] - log.truth[:, 2]) ** 2))),
            "heading_rms": float(np.sqrt(np.mean(wrap(dh - turn) ** 2))), "rotation": turn,
            "velocity_rms": np.sqrt(np.mean((aligned - tv) ** 2, axis=0)).tolist(),
            "curve_rms": (float(np.sqrt(np.mean((cal.model.reading(dist) - true_r) ** 2))) if sensor == "range"
                          else float("nan")),
            "sigma": float(sigma), "true_sigma": truth["noise"][f"{'reading' if sensor == 'range' else 'bearing'}_sigma"],
            "seconds": seconds}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--minutes", type=float, default=8.0)
    ap.add_argument("--sensor", choices=["range", "bearing"], default="range")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    rows = []
    print("seed | position RMS m | heading RMS rad | rotation rad | vx, vy mm/s, w rad/s RMS | curve m | sensor sigma (true) | s")
    for seed in a.seeds:
        r = one(seed, a.minutes, a.sensor)
        rows.append(r)
        v = r["velocity_rms"]
        print(f"{seed} | {r['position_rms']:.3f} | {r['heading_rms']:.3f} | {r['rotation']:+.3f} | "
              f"{1000 * v[0]:.1f}, {1000 * v[1]:.1f}, {v[2]:.3f} | {r['curve_rms']:.3f} | "
              f"{r['sigma']:.3f} ({r['true_sigma']}) | {r['seconds']:.0f}", flush=True)
    med = {k: float(np.median([r[k] for r in rows])) for k in ("position_rms", "heading_rms", "curve_rms")}
    vmed = np.median([r["velocity_rms"] for r in rows], axis=0)
    print(f"median | {med['position_rms']:.3f} | {med['heading_rms']:.3f} | | {1000 * vmed[0]:.1f}, "
          f"{1000 * vmed[1]:.1f}, {vmed[2]:.3f} | {med['curve_rms']:.3f} | |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
