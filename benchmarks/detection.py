"""Detection rates of ``diagnose``: hide each catalog effect at given strengths, diagnose, add, diagnose again.

Each trial simulates a log, calibrates the base model, diagnoses it, adds the verdict with
``calibrate --effect`` and diagnoses again (``casm_graph.pipeline.hidden_effect``). One JSON line per
trial goes to ``--out`` as it finishes, so a long run loses nothing; the table at the end is
what BENCHMARKS.md records.

    python benchmarks/detection.py --minutes 6 --seeds 0 1 2 [--effects actuator_lag=0.3,0.15 none]
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
from collections import defaultdict

from casm_graph.pipeline import hidden_effect

MODERATE = {"actuator_lag": [0.3], "battery_fade": [0.02], "surface_friction": [0.15],
            "camera_latency": [0.1], "lens_distortion": [0.3], "range_dependent_noise": [0.5],
            "false_detections": [0.05], "landmark_offset": [0.2], "none": [0.0]}


def parse(items: list[str]) -> dict[str, list[float]]:
    out = {}
    for it in items:
        name, _, vals = it.partition("=")
        out[name] = [float(v) for v in vals.split(",")] if vals else MODERATE[name]
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--effects", nargs="+", default=list(MODERATE))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--out", default="detection.jsonl")
    ap.add_argument("--no-after", action="store_true", help="skip the add-and-rediagnose step")
    ap.add_argument("--table", nargs="+", metavar="JSONL", help="only print the table of earlier runs' JSON lines")
    args = ap.parse_args()
    done = defaultdict(list)
    if args.table:
        for path in args.table:
            with open(path) as f:
                for line in f:
                    if line.strip():
                        row = json.loads(line)
                        done[(row["effect"] or "none", row["value"])].append(row)
        print_table(done)
        return
    with open(args.out, "a") as f:
        for name, values in parse(args.effects).items():
            for v in values:
                for seed in args.seeds:
                    with tempfile.TemporaryDirectory() as w:
                        tr = hidden_effect.run(None if name == "none" else name, v, seed, args.minutes, w,
                                               after=not args.no_after)
                    row = tr.to_json()
                    f.write(json.dumps(row, default=float) + "\n")
                    f.flush()
                    done[(name, v)].append(row)
                    print(f"{name}={v} seed {seed}: verdict {tr.verdict}, after {tr.verdict_after}, "
                          f"held-out gain {tr.heldout_gain}, score {tr.error_before['score']:.2f} -> "
                          f"{tr.error_after['score'] if tr.error_after else float('nan'):.2f}, {tr.seconds:.0f} s",
                          flush=True)
    print_table(done)


def print_table(done: dict) -> None:
    """Detection rate, fix rate, held-out gain and model error per (effect, strength)."""
    print("\n| effect | strength | detected | none after adding it | held-out gain (nats, median) | "
          "table+curve error before -> after (paper units, median) | parameter error with the effect's own, "
          "before -> after (median; falls on) | verdict per seed |")
    print("|---|---|---|---|---|---|---|---|")
    for (name, v), rows in done.items():
        want = "none" if name == "none" else name
        hit = sum(r["verdict"] == want for r in rows)
        after = [r for r in rows if r["verdict_after"] is not None]
        fixed = sum(r["verdict_after"] == "none" for r in after)
        gains = sorted(r["heldout_gain"] for r in rows if r["heldout_gain"] is not None)
        before = sorted(r["error_before"]["score"] for r in rows)
        aft = sorted(r["error_after"]["score"] for r in after)
        tb = {id(r): total(r["error_before"], {}, r["truth"]) for r in rows}
        ta = {id(r): total(r["error_after"], r["fitted"], r["truth"]) for r in after}
        falls = sum(ta[id(r)] < tb[id(r)] for r in after)
        med = (lambda x: f"{x[len(x) // 2]:.2f}" if x else "-")
        seeds = ", ".join(f"{r['seed']}: {r['verdict']}" for r in sorted(rows, key=lambda r: r["seed"]))
        print(f"| {name} | {v:g} | {hit}/{len(rows)} | {fixed}/{len(after)} | {med(gains)} | "
              f"{med(before)} -> {med(aft)} | {med(sorted(tb.values()))} -> {med(sorted(ta.values()))} "
              f"({falls}/{len(after)}) | {seeds} |")


def total(err: dict, fitted: dict, truth: dict) -> float:
    """``model_error``'s total; rows written before it existed get it from their score and effects."""
    if "total" in err:
        return err["total"]
    return float(math.hypot(err["score"], hidden_effect.effect_error(fitted or {}, truth or {})))


if __name__ == "__main__":
    main()
