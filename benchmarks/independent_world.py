"""Diagnosis on worlds written apart from the code: ``tests/worlds/independent_world.py`` (kinds ``table`` and
``continuous``) and ``tests/worlds/omni_world.py`` (kind ``omni``: an omnidirectional walker commanded ``vx, vy, w``,
seen by a camera's apparent size; no ``--min-range``, its camera sees from 0.4 m).

That generator shares nothing with casm_graph's simulator or effect code: its own random field and
landmarks, continuous-time motion at 200 Hz with slip, a sensor curve that is not a polynomial, and each
effect produced by physics (a second-order actuator lag, a carpet patch at a random place, a time-shifted
camera, ...) at a random strength. Each trial calibrates the base model, diagnoses it, adds the verdict
(or, when the verdict is not a catalog effect, the hidden effect's catalog name when it has one) and
diagnoses again; the error against the world's truth is the trajectory's position RMS. One JSON line per
trial goes to ``--out`` as it finishes; the table at the end is what BENCHMARKS.md records.

    OPENBLAS_NUM_THREADS=1 python benchmarks/independent_world.py --kinds table continuous --seeds 0 1 \\
        --effects none actuator_lag camera_latency lens_distortion --minutes 6
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                                    # noqa: E402
from casm_graph.analysis.groundtruth import trajectory_rms  # noqa: E402
from casm_graph.fit.continuous import check_effects       # noqa: E402
from casm_graph.io.log import LogError                    # noqa: E402
from casm_graph.models.effects import get as get_effect   # noqa: E402
from tests.worlds import generate_world, traces            # noqa: E402

CATALOG = {e["name"] for e in cg.catalog()}
UNCATALOGED = {"heading_speed": "heading", "position_drift_speed": "x", "time_speed": "time",
               "speed_turn": "speed"}   # the covariate each depends on


def addable(effect: str | None, log) -> bool:
    """Whether ``calibrate --effect effect`` takes ``log`` (a catalog effect its physics and channels allow)."""
    if effect not in CATALOG or get_effect(effect)(log).applicable(log) is not None:
        return False
    try:
        if log.controls is not None:
            check_effects([effect], log)
    except LogError:
        return False
    return True


def trial(kind: str, effect: str | None, seed: int, minutes: float, workdir: Path, min_range: float = 0.3,
          sensor_basis: str = "auto", options: cg.DiagnoseOptions | None = None, step_heading: str = "auto") -> dict:
    """One world (sightings no closer than ``min_range``): calibrate (the sensor curve in ``sensor_basis``),
    diagnose (as ``options`` say), add the named (or hidden) effect, diagnose again."""
    t0 = time.perf_counter()
    truth = generate_world(kind, workdir / "log", minutes, seed, effect,
                           **({} if kind == "omni" else {"min_range": min_range}))
    log = cg.load_log(workdir / "log")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = cg.calibrate(log, seed=seed, sensor_basis=sensor_basis, step_heading=step_heading)
        options = options or cg.DiagnoseOptions()
        d1 = cg.diagnose(log, base, options=options)
        add = d1.to_add() if d1.verdict in CATALOG else (effect if addable(effect, log) else None)
        row = {"kind": kind, "effect": effect or "none", "min_range": min_range, "sensor_basis": sensor_basis,
               "step_heading": step_heading,
               "basis": base.model.reading_basis, "strength": truth.get("strength"),
               "seed": seed, "minutes": minutes, "long_run_seconds": options.long_run_seconds, "verdict": d1.verdict,
               "lookalikes": [g["effects"] for g in d1.lookalikes],
               "candidates": [{"effect": c.effect, "delta_bic": c.delta_bic, "heldout": c.heldout_nll_drop,
                               "order": c.order} for c in d1.candidates[:4]],
               "error_before": trajectory_rms(base.trajectory, log.truth), "added": add,
               "trace": traces.check(d1, effect, truth.get("geometry") or truth.get("effect") or {}),
               "trends": trends(d1)}
        if add is not None:
            fixed = cg.calibrate(log, effects=[add], seed=seed, sensor_basis=sensor_basis, step_heading=step_heading)
            d2 = cg.diagnose(log, fixed, before=d1, options=options)
            row.update(verdict_after=d2.verdict, error_after=trajectory_rms(fixed.trajectory, log.truth),
                       trends_after=trends(d2),
                       predictive=d2.before_after.get("predictive") if d2.before_after else None)
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def trends(diag) -> dict:
    """Each moving motion channel's trend of the motion achieved: [rate per minute, t]."""
    return {ch: [r["trend"]["rate"], r["trend"]["t"]] for ch, r in diag.channels.items() if "trend" in r}


def wanted(row: dict) -> str:
    e = row["effect"]
    if e == "none":
        return "none"
    if e in UNCATALOGED:
        return f"unexplained:{UNCATALOGED[e]}"
    return e


def print_table(rows: list[dict]) -> None:
    groups = defaultdict(list)
    for r in rows:
        groups[(r["kind"], r.get("min_range", 0.3), r["effect"])].append(r)
    print("| kind | closest sighting, m | hidden effect | named right | wrong effect named | none (missed) | after adding: none | "
          "position RMS before -> after, m (median) |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for (kind, closest, eff), rs in sorted(groups.items()):
        want = wanted(rs[0])
        right = sum(r["verdict"] == want or any(want in g for g in r["lookalikes"]) for r in rs)
        missed = sum(r["verdict"] == "none" for r in rs) if want != "none" else 0
        wrong = len(rs) - right - missed
        after = [r for r in rs if "verdict_after" in r]
        none_after = sum(r["verdict_after"] == "none" for r in after)
        err = (f"{np.median([r['error_before'] for r in after]):.3f} -> {np.median([r['error_after'] for r in after]):.3f}"
               if after else f"{np.median([r['error_before'] for r in rs]):.3f}")
        print(f"| {kind} | {closest:g} | {eff} | {right}/{len(rs)} | {wrong}/{len(rs)} | {missed}/{len(rs)} | "
              f"{none_after}/{len(after)} | {err} |")


def print_traces(rows: list[dict]) -> None:
    """Per hidden catalog effect: how often the report opens with its view (first, or among the verdict's look-alikes'
    views) and how often that view shows it (tests/worlds/traces.py)."""
    groups = defaultdict(list)
    for r in rows:
        if (r.get("trace") or {}).get("expected"):
            groups[(r["kind"], r["effect"])].append(r["trace"])
    if not groups:
        return
    print("\n| kind | hidden effect | its view | first panel | among the opening views | the view shows it |")
    print("|---|---|---|---:|---:|---:|")
    for (kind, eff), ts in sorted(groups.items()):
        n = len(ts)
        print(f"| {kind} | {eff} | {ts[0]['expected']} | {sum(t['position'] == 0 for t in ts)}/{n} | "
              f"{sum(t['position'] is not None for t in ts)}/{n} | {sum(bool(t['shown']) for t in ts)}/{n} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kinds", nargs="+", default=["table", "continuous"])
    ap.add_argument("--effects", nargs="+", default=["none", "actuator_lag", "camera_latency", "lens_distortion"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--out", default="independent_world.jsonl")
    ap.add_argument("--min-range", type=float, default=0.3, help="closest sighting in the world, m")
    ap.add_argument("--sensor-basis", default="auto", choices=("auto", "distance", "inverse_distance"))
    ap.add_argument("--long-run-seconds", type=float, default=cg.DiagnoseOptions.long_run_seconds,
                    help="DiagnoseOptions.long_run_seconds: the motion residuals' long-run variance over this lag")
    ap.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    ap.add_argument("--table", nargs="+", metavar="JSONL", help="only print the table of earlier runs' JSON lines")
    args = ap.parse_args()
    if args.table:
        rows = [json.loads(line) for p in args.table for line in open(p) if line.strip()]
        print_table(rows)
        print_traces(rows)
        return
    rows = []
    with open(args.out, "a") as f:
        for kind in args.kinds:
            for effect in args.effects:
                for seed in args.seeds:
                    with tempfile.TemporaryDirectory() as w:
                        row = trial(kind, None if effect == "none" else effect, seed, args.minutes, Path(w),
                                    args.min_range, args.sensor_basis,
                                    cg.DiagnoseOptions(long_run_seconds=args.long_run_seconds), args.step_heading)
                    rows.append(row)
                    f.write(json.dumps(row, default=float) + "\n")
                    f.flush()
                    print(f"{kind} {row['effect']} seed {seed}: verdict {row['verdict']}"
                          + (f", after adding {row['added']}: {row.get('verdict_after')}" if row.get("added") else "")
                          + f" ({row['seconds']:.0f} s)", flush=True)
    print_table(rows)
    print_traces(rows)


if __name__ == "__main__":
    main()
