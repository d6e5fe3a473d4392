"""Actuator lag or camera latency? Each world of ``tests/worlds/independent_world.py`` (or ``omni_world.py``,
``--kind omni``) calibrated three times
(no effect, ``--effect actuator_lag``, ``--effect camera_latency``): the log-likelihood each calibration reaches
and its trajectory's position RMS against the world's truth; then the base diagnosed (the verdict, the look-alike
group, the diagnosis's seconds).

The diagnosis names one of the two look-alikes from fits on its coarse graph; this measures whether the
calibration's own graph separates them, and which one brings the trajectory to the truth.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lag_or_latency.py --effects camera_latency actuator_lag --seeds 0 1 3
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                                    # noqa: E402
from casm_graph.analysis.groundtruth import trajectory_rms  # noqa: E402
from tests.worlds import generate_world                    # noqa: E402

TRIED = ("actuator_lag", "camera_latency")


def trial(kind: str, effect: str, seed: int, minutes: float, workdir: Path) -> dict:
    """One world: the base and each of the two effects calibrated; log-likelihood, parameters, position RMS."""
    t0 = time.perf_counter()
    truth = generate_world(kind, workdir / "log", minutes, seed, effect)
    log = cg.load_log(workdir / "log")
    row = {"kind": kind, "effect": effect, "seed": seed, "minutes": minutes, "strength": truth.get("strength")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for added in (None, *TRIED):
            cal = cg.calibrate(log, effects=[added] if added else [], seed=seed)
            m = cal.model_json
            row[added or "base"] = {"log_likelihood": m["fit"].get("log_likelihood"),
                                    "parameters": m.get("effects", {}).get(added, {}) if added else {},
                                    "position_rms": trajectory_rms(cal.trajectory, log.truth)}
            if added is None:
                base = cal
        t1 = time.perf_counter()
        d = cg.diagnose(log, base)
        row["diagnosed"] = {"verdict": d.verdict, "lookalikes": [g["effects"] for g in d.lookalikes],
                            "seconds": round(time.perf_counter() - t1, 1)}
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def line(r: dict) -> str:
    lag, lat = r["actuator_lag"], r["camera_latency"]
    ahead = "camera_latency" if lat["log_likelihood"] > lag["log_likelihood"] else "actuator_lag"
    return (f"{r['kind']} {r['effect']} seed {r['seed']} (strength {r['strength']:.3g}): log-likelihood base "
            f"{r['base']['log_likelihood']:,.1f}, lag {lag['log_likelihood']:,.1f}, latency "
            f"{lat['log_likelihood']:,.1f} ({ahead} ahead by {abs(lat['log_likelihood'] - lag['log_likelihood']):,.1f}"
            f"); position RMS m base {r['base']['position_rms']:.4f}, lag {lag['position_rms']:.4f}, latency "
            f"{lat['position_rms']:.4f}; diagnosis {r['diagnosed']['verdict']} {r['diagnosed']['lookalikes']} "
            f"({r['diagnosed']['seconds']} s)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", default="continuous", choices=("continuous", "table", "omni"))
    ap.add_argument("--effects", nargs="+", default=["camera_latency", "actuator_lag"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--out", default="lag_or_latency.jsonl")
    args = ap.parse_args(argv)
    for effect in args.effects:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as tmp:
                r = trial(args.kind, effect, seed, args.minutes, Path(tmp))
            with open(args.out, "a") as f:
                f.write(json.dumps(r) + "\n")
            print(line(r), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
