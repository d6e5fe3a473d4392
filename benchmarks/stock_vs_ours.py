"""Time per LM iteration on the same full graph: our numpy-driven loop vs GTSAM's stock optimizer.

Both start from the same values (the simulator's truth, perturbed) on the same graph (a pose every
step, the CustomFactor graph of ``casm_graph.graph.table.build`` for the stock optimizer and its numpy
twin for ours) and run a fixed number of iterations, side by side in one process.

    python benchmarks/stock_vs_ours.py [--steps 3000 9000 27000] [--iterations 2]
"""
from __future__ import annotations

import argparse
import time

import gtsam
import numpy as np

from casm_graph.fit.solve import least_squares
from casm_graph.graph import table as G
from casm_graph.graph.problem import Problem
from casm_graph.models.model import paper_start
from casm_graph.sim.aibo import SimConfig, simulate


def setup(steps: int, seed: int = 0):
    log, truth = simulate(SimConfig(minutes=steps / 1800, seed=seed))
    rng = np.random.default_rng(seed)
    m = paper_start(log)
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids])
    m = m.with_(velocities=tv + rng.normal(0, 0.02, tv.shape),
                reading_poly=np.array(truth["sensor_model"]["reading_poly_best_cubic"]) * 1.05,
                reading_sigma=1.0, bearing_sigma=0.5, motion_noise=np.array([0.002, 0.002, 0.004]))
    lay = G.layout(log, m, 1)
    poses = log.truth[:, 1:] + rng.normal(0, [0.02, 0.02, 0.02], (lay.n_poses, 3))
    return log, m, lay, poses


def ours(log, m, lay, poses, iterations):
    t = time.perf_counter()
    problem = Problem(log, m, lay=lay)
    st, h = least_squares(problem, problem.state(poses, m), max_iterations=iterations, rel_tol=-1.0)
    return time.perf_counter() - t, h.iterations, problem.cost(st)


def stock(log, m, lay, poses, iterations):
    t = time.perf_counter()
    graph = G.build(log, lay, m)
    values = G.values(poses, m)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(0.0)
    params.setAbsoluteErrorTol(0.0)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return time.perf_counter() - t, opt.iterations(), graph.error(result)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, nargs="+", default=[3000, 9000, 27000])
    ap.add_argument("--iterations", type=int, default=2)
    args = ap.parse_args()
    ours(*setup(300), 1)              # numba compiles the chain kernels on first use: not part of an iteration
    print("| steps | ours s/iter | stock s/iter | ratio stock/ours | final cost ours | final cost stock |")
    print("|---|---|---|---|---|---|")
    for steps in args.steps:
        data = setup(steps)
        t_o, n_o, c_o = ours(*data, args.iterations)
        t_s, n_s, c_s = stock(*data, args.iterations)
        print(f"| {steps} | {t_o / n_o:.2f} | {t_s / n_s:.2f} | {(t_s / n_s) / (t_o / n_o):.1f} | {c_o:.1f} | {c_s:.1f} |",
              flush=True)


if __name__ == "__main__":
    main()
