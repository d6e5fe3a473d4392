"""How a MRCLAM robot's calibration depends on the range sensor's start slope, and what picking by likelihood gives.

    OPENBLAS_NUM_THREADS=1 python benchmarks/start_slopes.py --robot 4 [--factors 0.88 0.92 0.96 1.0 1.04]

Per start slope (the sensor hypothesis's slope times a factor of ``continuous.SLOPE_FACTORS``): the whole
continuous fit from that one start, its log-likelihood after the held coarse rounds (what the fit compares
its ``SLOPE_STARTS`` best-agreeing slopes by) and at the end, and the maps and trajectory against Vicon. Then
the fit as shipped (the three slopes, the likeliest goes on).
"""
import argparse
import tempfile
import time
from pathlib import Path


from casm_graph.analysis import groundtruth
from casm_graph.fit import continuous
from casm_graph.fit.windows import WindowOptions
from casm_graph.io import mrclam
from casm_graph.io.log import load


def judged(log, fit) -> str:
    ref = groundtruth.truth_fit(log, fit.model.command)
    err = groundtruth.map_errors(fit.model.command, ref, log.controls, log.dt)
    pos = groundtruth.position_rms(fit.poses, log.truth)
    return (f"{100 * err['w']['fraction']:.1f} | {100 * err['v']['fraction']:.1f} | {pos:.3f} | "
            f"{fit.log_likelihood:,.0f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=None, help="the MRCLAM dataset directory (default: found as the tests find it)")
    ap.add_argument("--robot", type=int, default=4)
    ap.add_argument("--factors", type=float, nargs="*", default=None, help="default: all of WindowOptions().slope_factors")
    a = ap.parse_args()
    data = Path(a.data) if a.data else mrclam.find_data()
    with tempfile.TemporaryDirectory() as tmp:
        mrclam.import_robot(data, a.robot, Path(tmp) / "log")
        log = load(Path(tmp) / "log")
    factors = WindowOptions().slope_factors
    print(f"robot {a.robot}\n\n| start slope factor | slope | log-likelihood after the held rounds | turn map % | "
          "speed map % | position RMS m | final log-likelihood | seconds |\n|---|---|---|---|---|---|---|---|")
    for f in (a.factors if a.factors is not None else factors):
        t0 = time.perf_counter()
        fit = continuous.fit(log, marginals=False, start_options=WindowOptions(slope_factors=(f,), slope_starts=1))
        (slope, held), = fit.model.fit["start_slopes"]
        print(f"| {f:.4f} | {slope:.3f} | {held:,.0f} | {judged(log, fit)} | {time.perf_counter() - t0:.0f} |", flush=True)
    t0 = time.perf_counter()
    fit = continuous.fit(log, marginals=False)
    tried = ", ".join(f"{s:.3f} ({h:,.0f})" for s, h in fit.model.fit["start_slopes"])
    print(f"\nas shipped: slopes tried {tried}; chose {fit.notes['start_slope']:.3f}: turn %, speed %, position m, "
          f"log-likelihood {judged(log, fit)}; {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
