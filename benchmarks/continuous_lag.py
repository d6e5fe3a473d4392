"""The actuator_lag profile on simulated continuous-command floors: found when there, and how often when not.

    OPENBLAS_NUM_THREADS=1 python benchmarks/continuous_lag.py --seeds 0 1 2 3 4 5 --lags 0 0.3

Per floor (simulate_floor, 4 minutes, 0.1 s steps): the graph calibration, then
:func:`casm_graph.continuous.profile`; prints the fitted lag, the profile's log-likelihood gain
and delta BIC (below -10 counts as strong evidence, the diagnosis's threshold).
"""
from __future__ import annotations

import argparse
import time

from casm_graph import continuous
from casm_graph.diagnose import BIC_SUPPORT
from casm_graph.simulate_floor import FloorConfig, simulate


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--lags", type=float, nargs="+", default=[0.0, 0.3])
    ap.add_argument("--minutes", type=float, default=4.0)
    a = ap.parse_args()
    print("| true lag s | seed | fitted lag s | log-likelihood gain | delta BIC | strong evidence | seconds |")
    print("|---|---|---|---|---|---|---|")
    for lag in a.lags:
        for seed in a.seeds:
            log, _ = simulate(FloorConfig(minutes=a.minutes, seed=seed, dt=0.1, lag=lag))
            t0 = time.perf_counter()
            fit = continuous.fit(log, continuous.start_model(log), seed=seed, marginals=False)
            prof = continuous.profile(log, fit, "actuator_lag")
            dbic = prof.delta_bic
            print(f"| {lag:g} | {seed} | {prof.value:.3f} | {prof.gain:.1f} | {dbic:.1f} | "
                  f"{'yes' if dbic <= BIC_SUPPORT else 'no'} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
