"""The continuous-log diagnosis of one effect on simulated floors: found when there, and how often when not.

    OPENBLAS_NUM_THREADS=1 python benchmarks/continuous_effects.py --effect actuator_lag --values 0 0.3 --seeds 0 1 2 3 4 5
    OPENBLAS_NUM_THREADS=1 python benchmarks/continuous_effects.py --effect lens_distortion --values 0 -0.1 --seeds 0 1 2 3 4 5

Per floor (simulate_floor, 4 minutes, 0.1 s steps, the effect at the given true value): the graph calibration,
then ``diagnose`` with that one candidate (the lag profiled in the command model, the lens fitted through its
hook); prints the fitted value, the candidate's delta BIC (at most -10 counts as strong evidence, the
diagnosis's threshold) and the verdict, which also needs the residual structure the effect is built for.
"""
from __future__ import annotations

import argparse
import time
import warnings

import casm_graph as cg
from casm_graph.analysis.diagnosis import BIC_SUPPORT
from casm_graph.sim.floor import FloorConfig, simulate

SWITCH = {"actuator_lag": ("lag", "tau"), "lens_distortion": ("lens_k", "k")}   # simulator option, parameter


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--effect", choices=sorted(SWITCH), default="actuator_lag")
    ap.add_argument("--values", type=float, nargs="+", default=[0.0, 0.3])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--minutes", type=float, default=4.0)
    a = ap.parse_args()
    option, param = SWITCH[a.effect]
    print(f"| {a.effect}: true | seed | fitted {param} | delta BIC | strong evidence | verdict | seconds |")
    print("|---|---|---|---|---|---|---|")
    for value in a.values:
        for seed in a.seeds:
            log, _ = simulate(FloorConfig(minutes=a.minutes, seed=seed, dt=0.1, **{option: value}))
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                base = cg.calibrate(log, seed=seed)
                diag = cg.diagnose(log, base, candidates=[a.effect])
            c = next(c for c in diag.candidates if c.effect == a.effect)
            print(f"| {value:g} | {seed} | {c.parameters.get(param, float('nan')):.3f} | {c.delta_bic:.1f} | "
                  f"{'yes' if c.delta_bic <= BIC_SUPPORT else 'no'} | {diag.verdict} | "
                  f"{time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
