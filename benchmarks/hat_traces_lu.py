"""The noise step's sparse LU side by side: SuperLU with partial pivoting (before 2026-11-25) and without
pivoting in symmetric mode (now; the information matrix is symmetric positive definite).

    OPENBLAS_NUM_THREADS=1 python benchmarks/hat_traces_lu.py [--minutes 4] [--repeats 5]

On the Jacobian of a continuous-command floor log at the initialiser's start (the problem the noise
step factors every round), prints fill, factor and 24-probe solve times (medians) and the largest
relative difference of the solutions.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.sparse.linalg import splu

from casm_graph.fit import continuous as CT
from casm_graph.graph.problem import Problem
from casm_graph.sim.floor import FloorConfig, simulate


def timed(f, repeats):
    out, ts = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return out, float(np.median(ts))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=4.0)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    log, _ = simulate(FloorConfig(minutes=a.minutes, seed=1, dt=0.1, lens_k=-0.1, detect_prob=0.4))
    start = CT.initialise(log, CT.start_model(log))
    lay = CT.layout(log, CT.DEFAULTS.coarse_knot_dt)
    problem = Problem(log, start.model, lay=lay, poses=start.poses[lay.knots])
    A, _, groups = problem.jacobian(problem.state(start.poses[lay.knots], start.model))
    H = (A.T @ A).tocsc()
    rows = groups["forward"]
    U = np.asarray(A[rows].T @ np.random.default_rng(0).choice([-1.0, 1.0], size=(len(rows), 24)))
    print(f"Jacobian {A.shape[0]} x {A.shape[1]}, information matrix nnz {H.nnz}")
    print("| LU | fill (nnz L + U) | factor s | solve, 24 probes, s |")
    print("|---|---|---|---|")
    sol = {}
    for name, kw in (("partial pivoting (before)", {"permc_spec": "MMD_AT_PLUS_A"}),
                     ("no pivoting, symmetric mode (now)", {"permc_spec": "MMD_AT_PLUS_A", "diag_pivot_thresh": 0.0,
                                                            "options": {"SymmetricMode": True}})):
        lu, tf = timed(lambda: splu(H, **kw), a.repeats)
        sol[name], ts = timed(lambda: lu.solve(U), a.repeats)
        print(f"| {name} | {lu.L.nnz + lu.U.nnz} | {tf:.3f} | {ts:.3f} |")
    x0, x1 = sol.values()
    print(f"largest relative difference of the solutions: {np.abs(x1 - x0).max() / np.abs(x0).max():.1e}")


if __name__ == "__main__":
    main()
