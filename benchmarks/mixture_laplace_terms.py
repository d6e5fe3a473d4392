"""Why the held-out folds misjudge false_detections: the terms of the Laplace log-likelihood along a fold fit.

Calibrates a log with 5 % false detections hidden, fits the mixture effect as ``diagnose`` does,
then runs the fold fit's call (effects and noise held) for 0, 1 and 4 iterations from that optimum
and prints the log-likelihood split by ``Problem.log_likelihood_terms``: motion and
observation densities, the poses' Gaussian constant and half the log determinant of their information. Least squares climbs the joint density (motion + observation);
the Laplace term is what moves the other way.

    python benchmarks/mixture_laplace_terms.py --seed 1
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from casm_graph.analysis import diagnosis
from casm_graph.analysis.candidates import table
from casm_graph.fit import effect_fit
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.sim.aibo import SimConfig, simulate, write


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fraction", type=float, default=0.05)
    a = ap.parse_args()
    w = Path(tempfile.mkdtemp())
    log, truth = simulate(SimConfig(minutes=6, seed=a.seed, effects={"false_detections": a.fraction}))
    write(log, truth, w / "log")
    log, fit = calibrate_run.run(w / "log", w / "run", seed=a.seed)
    kw = {"rounds": diagnosis.DEFAULTS.candidate_rounds, "iterations": diagnosis.DEFAULTS.candidate_iterations}
    refit = effect_fit.fit(log, fit.model, fit.poses, [], **kw)
    base = effect_fit.fit(log, refit.model, refit.poses, [], **kw)
    _, m, p = table.fit_candidate(log, refit, base, "false_detections")
    opt = effect_fit.fit(log, m, p, ["false_detections"], **kw)
    for its in (0, 1, 4):
        f = effect_fit.fit(log, opt.model, opt.poses, ["false_detections"], theta=opt.theta, rounds=1,
                           iterations=its, fit_noise=False, rel_tol=diagnosis.DEFAULTS.fold_tol)
        t = f.problem.log_likelihood_terms(f.state)
        print(f"{its} iterations: log-likelihood {f.log_likelihood:.1f}, " + ", ".join(f"{k} {v:.1f}" for k, v in t.items())
              + f", joint density {t['motion'] + t['observation']:.1f}", flush=True)


if __name__ == "__main__":
    main()
