"""Bad data against the table's error: wild readings, swapped landmark ids, false detections.

    OPENBLAS_NUM_THREADS=1 python benchmarks/robustness.py [--minutes 6] [--seeds 0 1] [--cases clean wild1 ...]

Per seed: a simulated Aibo log (clean), then the same log with one reading multiplied by 10,000
(``wild1``), five such readings (``wild5``), 2 % of the sightings given another landmark's id
(``swap2``), and a log simulated with 20 % false detections, calibrated without and with the
``false_detections`` effect (``false20``, ``false20+fx``). Prints each case's velocity-table RMS
error against the truth (mm/s, mm/s, rad/s), the sensor curve's error (px), the reading sigma and
the exit status, beside the clean log's, and the ratio to clean that the targets are stated in.
"""
from __future__ import annotations

import argparse

from casm_graph.pipeline.bad_data import CASES, trial


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    a = ap.parse_args()
    rows = [trial(c, s, a.minutes) for s in a.seeds for c in a.cases]
    clean = {r["seed"]: r for r in rows if r["case"] == "clean" and r["status"] == "ok"}
    print("| case | seed | vx mm/s | vy mm/s | w rad/s | curve px | reading sigma | vx, vy / clean | status |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["status"] != "ok":
            print(f"| {r['case']} | {r['seed']} | | | | | | | {r['status']} |")
            continue
        c = clean.get(r["seed"])
        ratio = f"{r['vx'] / c['vx']:.2f}, {r['vy'] / c['vy']:.2f}" if c else ""
        print(f"| {r['case']} | {r['seed']} | {r['vx']:.1f} | {r['vy']:.1f} | {r['w']:.4f} | {r['curve']:.2f} | "
              f"{r['reading_sigma']:.3g} | {ratio} | {'converged' if r['converged'] else 'not converged'} |")


if __name__ == "__main__":
    main()
