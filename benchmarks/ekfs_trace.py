"""EKFS-EM per iteration on one simulated log: likelihood, table error, and the actions that move most.

Shows whether the likelihood rises until approximation noise (the paper) or cycles between states.

    python benchmarks/ekfs_trace.py --minutes 15 --seed 3 --iterations 200
"""
from __future__ import annotations

import argparse

import numpy as np

from casm_graph.fit.methods import ekfs_em
from casm_graph.models.model import paper_start
from casm_graph.sim.aibo import SimConfig, simulate


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=15)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=200)
    a = ap.parse_args()
    log, truth = simulate(SimConfig(minutes=a.minutes, seed=a.seed))
    start = paper_start(log)
    fit = ekfs_em.fit(log, start, seed=a.seed, truth=truth, max_iterations=a.iterations, patience=a.iterations)
    h = fit.notes["history"]
    print(f"pruned {fit.model.fit['outliers_pruned']} of {int(np.isfinite(log.obs_reading).sum())} sightings; "
          f"best iteration {fit.model.fit['best_iteration']}")
    for i, (ll, e, hd) in enumerate(zip(h["log_likelihood"], h["velocity_rms"], h["heading_rms"])):
        if i < 30 or i % 10 == 0:
            print(f"{i:4d}  log-likelihood {ll:10.1f}  vx {1000 * e[0]:6.1f} vy {1000 * e[1]:6.1f} mm/s  w {e[2]:.4f} rad/s"
                  f"  forward-filter heading RMS {hd:.3f} rad")
    V = np.array(h["velocities"])
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in start.action_ids])
    for k in np.argsort(-np.abs(V[-1, :, 2] - tv[:, 2]))[:4]:
        print(f"action {start.action_ids[k]}: true w {tv[k, 2]:.3f}; last six iterations "
              + " ".join(f"{w:.3f}" for w in V[-6:, k, 2]))


if __name__ == "__main__":
    main()
