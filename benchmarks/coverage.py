"""Coverage of the 90 % credible intervals of ``casm-graph uncertainty`` over simulated seeds.

Each seed: simulate a log, calibrate it with the graph method (from the paper's start, as a user
would), run the uncertainty computation on the calibrated model, and record whether each sampled
quantity's 90 % interval and each velocity-table component's Laplace 90 % interval contain the
simulator's truth. One JSON line per seed goes to --out as it finishes; --table prints the
markdown table of a finished file.

    python benchmarks/coverage.py --minutes 3 --seeds $(seq 0 19) --out coverage.jsonl
    python benchmarks/coverage.py --table coverage.jsonl
"""
from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

from casm_graph.fit.methods import METHODS
from casm_graph.models.model import paper_start
from casm_graph.pipeline.uncertainty import compute
from casm_graph.report.uncertainty import true_table, true_values
from casm_graph.sim.aibo import SimConfig, simulate

Z90 = 1.6448536269514722


def one(minutes: float, seed: int) -> dict:
    log, truth = simulate(SimConfig(minutes=minutes, seed=seed))
    t0 = time.perf_counter()
    fit = METHODS["graph"](log, paper_start(log), seed=seed, marginals=False)
    t_cal = time.perf_counter() - t0
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        unc = compute(log, fit.model, fit.poses, seed=seed, truth=truth)
    tv = true_values(unc)
    rec = {"seed": seed, "minutes": minutes, "calibrate_s": round(t_cal, 1), "uncertainty_s": round(unc.seconds, 1),
           "ms_per_eval": 1000 * unc.chain.seconds_per_evaluation, "evaluations": unc.chain.evaluations,
           "steps": unc.chain.steps, "walkers": unc.chain.walkers, "tau_max": float(np.max(unc.chain.tau)),
           "too_short": unc.chain.too_short, "quantities": {}}
    for n, s in unc.intervals.items():
        t = tv.get(n)
        rec["quantities"][n] = {"median": s["median"], "ci90": s["ci90"], "truth": t,
                                "inside": None if t is None else bool(s["ci90"][0] <= t <= s["ci90"][1])}
    tt = true_table(unc)
    z = np.abs(unc.model.velocities - tt) / unc.model.velocity_std
    rec["velocity_inside"] = (z <= Z90).sum(axis=0).tolist()
    rec["velocity_n"] = int(len(z))
    return rec


def table(path: str) -> str:
    recs = [json.loads(line) for line in open(path) if line.strip()]
    names = list(recs[0]["quantities"])
    lines = ["| seed | " + " | ".join(names) + " | velocity table (vx, vy, w) | tau max | steps | s/eval ms | seconds |",
             "|---" * (len(names) + 6) + "|"]
    for r in recs:
        cells = []
        for n in names:
            q = r["quantities"][n]
            mark = "" if q["inside"] else " **out**"
            cells.append(f"{q['median']:.3g} [{q['ci90'][0]:.3g}, {q['ci90'][1]:.3g}]{mark}")
        v = r["velocity_inside"]
        cells.append(f"{v[0]}/{r['velocity_n']}, {v[1]}/{r['velocity_n']}, {v[2]}/{r['velocity_n']}")
        lines.append(f"| {r['seed']} | " + " | ".join(cells) + f" | {r['tau_max']:.0f} | {r['steps']} | "
                     f"{r['ms_per_eval']:.1f} | {r['uncertainty_s']:.0f} |")
    n = len(recs)
    cover = [f"{n_}: {sum(r['quantities'][n_]['inside'] for r in recs)}/{n} "
             f"({100 * np.mean([r['quantities'][n_]['inside'] for r in recs]):.0f} %)" for n_ in names]
    vin = np.sum([r["velocity_inside"] for r in recs], axis=0)
    vn = sum(r["velocity_n"] for r in recs)
    lines.append("")
    lines.append("coverage of the 90 % intervals: " + "; ".join(cover))
    lines.append(f"velocity table (Laplace): vx {100 * vin[0] / vn:.1f} %, vy {100 * vin[1] / vn:.1f} %, "
                 f"w {100 * vin[2] / vn:.1f} % of {vn} intervals each; all {100 * vin.sum() / (3 * vn):.1f} %")
    lines.append(f"autocorrelation time / chain length: max {max(r['tau_max'] / r['steps'] for r in recs):.3f}; "
                 f"chains too short: {sum(r['too_short'] for r in recs)}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(20)))
    ap.add_argument("--out", default="coverage.jsonl")
    ap.add_argument("--table", metavar="JSONL", help="print the table of a finished run and exit")
    args = ap.parse_args()
    if args.table:
        print(table(args.table))
        return
    for seed in args.seeds:
        rec = one(args.minutes, seed)
        with open(args.out, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(seed, {n: q["inside"] for n, q in rec["quantities"].items()}, rec["velocity_inside"],
              f"{rec['uncertainty_s']:.0f} s", flush=True)
    print(table(args.out))


if __name__ == "__main__":
    main()
