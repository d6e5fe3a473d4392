"""Continuous-command figures to hold across a restructuring: one JSON line per case, and a comparison of two runs.

Cases: the independent world's continuous robot (3 minutes, seed 1) effect-free and with each catalog effect
hidden, calibrated without and with it (``cg.calibrate(log, effects=[name])``); on the effect-free log the
diagnosis, the uncertainty (16 walkers x 400 steps) and regional motion noise; the first 8 minutes of Plaza 1
when the data are there. Each line holds the command map, the curve, the noise levels, the log-likelihood, the
effects and the position RMS against the truth.

    OPENBLAS_NUM_THREADS=1 python benchmarks/command_logs.py --out after.jsonl
    PYTHONPATH=/path/to/previous/release python benchmarks/command_logs.py --out before.jsonl
    python benchmarks/command_logs.py --compare before.jsonl after.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))   # tests.worlds; PYTHONPATH still picks casm_graph

import casm_graph as cg  # noqa: E402
from casm_graph.io import plaza  # noqa: E402
from tests.worlds.independent_world import generate  # noqa: E402

EFFECTS = ("battery_fade", "camera_latency", "false_detections", "range_dependent_noise", "actuator_lag",
           "lens_distortion", "landmark_offset")


def rms(log, cal) -> float:
    tr = cal.trajectory
    return float(np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)))


def figures(log, cal) -> dict:
    m = cal.model
    return {"params": np.round(m.command.params, 6).tolist(), "poly": np.round(m.reading_poly, 6).tolist(),
            "noise": np.round(np.r_[m.motion_noise, m.reading_sigma, m.bearing_sigma], 6).tolist(),
            "ll": round(float(m.fit["log_likelihood"]), 3), "effects": m.effects,
            "rms": round(rms(log, cal), 5) if log.truth is not None else None}


def run(out: Path) -> None:
    with open(out, "w") as f, tempfile.TemporaryDirectory() as tmp:
        def emit(case: str, d: dict) -> None:
            f.write(json.dumps({"case": case, **d}, default=float) + "\n")
            f.flush()
            print(case, file=sys.stderr, flush=True)

        for eff in ("none", *EFFECTS):
            d = Path(tmp) / eff
            generate(d, kind="continuous", minutes=3, seed=1, effect=None if eff == "none" else eff)
            log = cg.load_log(d)
            t = time.perf_counter()
            cal = cg.calibrate(log)
            emit(f"{eff}/base", {**figures(log, cal), "s": round(time.perf_counter() - t, 1)})
            if eff == "none":
                dg = cg.diagnose(log, cal)
                emit("none/diagnose", {"verdict": dg.verdict,
                                       "cands": [[c.effect, round(c.delta_bic, 1)] for c in dg.candidates]})
                u = cg.uncertainty(log, cal, walkers=16, max_steps=400, seed=0)
                emit("none/uncertainty", {"intervals": u.intervals})
                emit("none/regional", figures(log, cg.calibrate(log, effects=["regional_motion_noise"])))
            else:
                cal2 = cg.calibrate(log, effects=[eff])
                emit(f"{eff}/with", {**figures(log, cal2), "std": cal2.model.fit.get("effects_std")})
        mat = plaza.find_plaza()
        if mat is not None:
            log = plaza.load_plaza(mat, minutes=8)
            emit("plaza8", figures(log, cg.calibrate(log)))


def compare(a_path: str, b_path: str) -> None:
    a = {json.loads(line)["case"]: json.loads(line) for line in open(a_path)}
    b = {json.loads(line)["case"]: json.loads(line) for line in open(b_path)}
    for k, x in a.items():
        y = b.get(k)
        if y is None:
            print(f"{k}: missing from {b_path}")
        elif "params" in x:
            dp = np.max(np.abs(np.subtract(x["params"], y["params"])) / np.maximum(np.abs(x["params"]), 1e-3))
            dn = np.max(np.abs(np.log(np.divide(y["noise"], x["noise"]))))
            print(f"{k:28s} position RMS {x['rms']} -> {y['rms']}, log-likelihood {x['ll']:.1f} -> {y['ll']:.1f}, "
                  f"largest relative map change {dp:.1e}, largest noise-level change {dn:.1e} (log)")
        elif "verdict" in x:
            print(f"{k}: {x['verdict']} -> {y['verdict']}; {x['cands'][:3]} -> {y['cands'][:3]}")
        else:
            for n in x["intervals"]:
                print(f"{k} {n}: {x['intervals'][n]['ci90']} -> {y['intervals'][n]['ci90']}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="write one JSON line per case here")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), help="compare two runs' files")
    a = ap.parse_args(argv)
    if a.compare:
        compare(*a.compare)
    elif a.out:
        run(Path(a.out))
    else:
        ap.error("give --out or --compare")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
