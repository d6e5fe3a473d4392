"""What lag the Vicon truth itself implies for each MRCLAM robot (a check on the actuator_lag the logs give).

    OPENBLAS_NUM_THREADS=1 python benchmarks/vicon_lag.py [--robots 1 2 3 4 5]

Per lag tau: the command-map form with that lag fitted with the poses held at Vicon
(:func:`casm_graph.analysis.groundtruth.truth_fit`), and the RMS of what it leaves unexplained over 1-s
segments; the lag where the turn residual is smallest is the one the truth supports.
"""
from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

import factors
from casm_graph.analysis import groundtruth
from casm_graph.fit import continuous as CT
from casm_graph.io import mrclam
from casm_graph.models.command_model import for_commands

TAUS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(mrclam.find_data()))
    ap.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    a = ap.parse_args()
    print("| robot | " + " | ".join(f"tau {t:g} s" for t in TAUS) + " | best |")
    print("|---|" + "---|" * (len(TAUS) + 1))
    for r in a.robots:
        log, _ = mrclam.import_robot(Path(a.data), r, Path(tempfile.mkdtemp()))
        lay = CT.layout(log, 1.0)
        P = log.truth[lay.knots, 1:]
        turn = []
        for tau in TAUS:
            ref = groundtruth.truth_fit(log, replace(for_commands(log.controls, 2, 1, gain=1.0), lag=tau))
            bv, _, bw = ref.basis(log.controls, log.dt)
            e, _ = factors.command.error(P[:-1], P[1:], ref.params, bv[lay.seg_idx], bw[lay.seg_idx], lay.seg_dt)
            turn.append(float(np.sqrt(np.mean(e[:, 2] ** 2))))
        print(f"| {r} | " + " | ".join(f"{x:.4f}" for x in turn) + f" | {TAUS[int(np.argmin(turn))]:g} s |", flush=True)
    print("(turn residual RMS over 1-s segments, rad)")


if __name__ == "__main__":
    main()
