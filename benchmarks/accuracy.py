"""Full-size accuracy of ``calibrate --method graph`` against the simulator's truth.

    python benchmarks/accuracy.py --minutes 15 --seeds 0 1 2 3 4
    python benchmarks/accuracy.py --minutes 6 --seeds $(seq 0 19)
    python benchmarks/accuracy.py --minutes 15 --seeds 0 1 2 3 4 --method ekfs-em [--outlier-m2 27.6]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from casm_graph.fit.methods import METHODS, ekfs_em
from casm_graph.models.model import paper_start
from casm_graph.sim.aibo import SimConfig, simulate, true_reading


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=15)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--method", choices=sorted(METHODS), default="graph")
    ap.add_argument("--outlier-m2", type=float, help="ekfs-em: first-iteration pruning threshold "
                    f"(squared Mahalanobis innovation; default {ekfs_em.OUTLIER_M2})")
    args = ap.parse_args()
    print("| seed | vx RMS mm/s | vy RMS mm/s | w RMS rad/s | curve RMS px | reading sigma | bearing sigma | "
          "iterations | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")
    ws, pruned = [], []
    extra = {"marginals": False} if args.method == "graph" else {}
    if args.outlier_m2:
        extra["outlier_m2"] = args.outlier_m2
    for seed in args.seeds:
        log, truth = simulate(SimConfig(minutes=args.minutes, seed=seed))
        t = time.perf_counter()
        fit = METHODS[args.method](log, paper_start(log), seed=seed, **extra)
        sec = time.perf_counter() - t
        tv = np.array([truth["action_model"]["velocities"][str(a)] for a in fit.model.action_ids])
        rms = np.sqrt(np.mean((fit.model.velocities - tv) ** 2, axis=0))
        d = np.linspace(*fit.model.distance_range, 200)
        curve = np.sqrt(np.mean((fit.model.reading(d) - true_reading(truth, d)) ** 2))
        ws.append(rms[2])
        if "best_iteration" in fit.model.fit:
            pruned.append((fit.model.fit["outliers_pruned"], fit.model.fit["best_iteration"]))
        print(f"| {seed} | {1000 * rms[0]:.1f} | {1000 * rms[1]:.1f} | {rms[2]:.4f} | {curve:.3f} | "
              f"{fit.model.reading_sigma:.3f} | {fit.model.bearing_sigma:.3f} | {fit.model.fit.get('iterations', '-')} | "
              f"{sec:.1f} |", flush=True)
    ok = sum(w < 0.1 for w in ws)
    print(f"\nglobal optimum (w RMS < 0.1 rad/s) on {ok} of {len(ws)} seeds")
    if pruned:
        print("sightings pruned, best iteration per seed: " + ", ".join(
            f"{s}: {n}, {b}" for s, (n, b) in zip(args.seeds, pruned)))


if __name__ == "__main__":
    main()
