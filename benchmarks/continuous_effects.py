"""The continuous-log effects' profiles on simulated floors: found when there, and how often when not.

    OPENBLAS_NUM_THREADS=1 python benchmarks/continuous_effects.py --effect actuator_lag --values 0 0.3 --seeds 0 1 2 3 4 5
    OPENBLAS_NUM_THREADS=1 python benchmarks/continuous_effects.py --effect lens_distortion --values 0 -0.1 --seeds 0 1 2 3 4 5

Per floor (simulate_floor, 4 minutes, 0.1 s steps, the effect at the given true value): the graph
calibration, then :func:`casm_graph.fit.continuous.profile`; prints the fitted value, the profile's
log-likelihood gain and delta BIC (at most -10 counts as strong evidence, the diagnosis's threshold).
"""
from __future__ import annotations

import argparse
import time

from casm_graph.analysis.diagnosis import BIC_SUPPORT
from casm_graph.fit import continuous
from casm_graph.sim.floor import FloorConfig, simulate

SWITCH = {"actuator_lag": "lag", "lens_distortion": "lens_k"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--effect", choices=sorted(SWITCH), default="actuator_lag")
    ap.add_argument("--values", type=float, nargs="+", default=[0.0, 0.3])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--minutes", type=float, default=4.0)
    a = ap.parse_args()
    print(f"| {a.effect}: true | seed | fitted | stages | log-likelihood gain | delta BIC | strong evidence | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for value in a.values:
        for seed in a.seeds:
            log, _ = simulate(FloorConfig(minutes=a.minutes, seed=seed, dt=0.1, **{SWITCH[a.effect]: value}))
            t0 = time.perf_counter()
            fit = continuous.fit(log, continuous.start_model(log), seed=seed, marginals=False)
            prof = continuous.profile(log, fit, a.effect)
            print(f"| {value:g} | {seed} | {prof.value:.3f} | {prof.order} | {prof.gain:.1f} | {prof.delta_bic:.1f} | "
                  f"{'yes' if prof.delta_bic <= BIC_SUPPORT else 'no'} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
