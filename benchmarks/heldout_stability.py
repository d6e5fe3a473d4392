"""Held-out gain of a hidden effect, and how much it moves with the fold fits' iteration count.

Simulates a log with ``EFFECT=VALUE`` hidden, calibrates it, fits the effect as ``diagnose`` does
and prints the held-out log-likelihood of the base model and of the model with the effect, for
each fold iteration count. A score worth trusting barely moves between 4 and 16 iterations.

    python benchmarks/heldout_stability.py lens_distortion 0.3 --seed 0 --iterations 4 16
    python benchmarks/heldout_stability.py false_detections 0.05 --seed 1 --iterations 4 --folds

``--folds`` also prints each fold's log-likelihoods: the fit with the block and without it.
"""
from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

from casm_graph.analysis import diagnosis
from casm_graph.analysis.candidates import table
from casm_graph.fit import effect_fit
from casm_graph.io.log import load
from casm_graph.models.effects import REGISTRY
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.sim.aibo import SimConfig, simulate, write


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("effect", choices=sorted(REGISTRY))
    ap.add_argument("value", type=float)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--iterations", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--folds", action="store_true", help="print every fold's terms")
    a = ap.parse_args()
    w = Path(tempfile.mkdtemp())
    log, truth = simulate(SimConfig(minutes=a.minutes, seed=a.seed, effects={a.effect: a.value}))
    write(log, truth, w / "log")
    _, fit = calibrate_run.run(w / "log", w / "run", seed=a.seed)
    log = load(w / "log")
    kw = {"rounds": diagnosis.DEFAULTS.candidate_rounds, "iterations": diagnosis.DEFAULTS.candidate_iterations}
    refit = effect_fit.fit(log, fit.model, fit.poses, [], **kw)
    base = effect_fit.fit(log, refit.model, refit.poses, [], **kw)
    cand, model, poses = table.fit_candidate(log, refit, base, a.effect)
    for n in a.iterations:
        opts = replace(diagnosis.DEFAULTS, fold_iterations=n)
        db, de = [], []
        hb = table.heldout_log_likelihood(log, base.model, base.poses, [], detail=db, options=opts)
        he = table.heldout_log_likelihood(log, model, poses, [REGISTRY[a.effect]], detail=de, options=opts)
        if a.folds:
            for label, rows in (("base", db), (a.effect, de)):
                for i, r in enumerate(rows):
                    print(f"  {label} fold {i}: " + ", ".join(f"{k} {v:.1f}" for k, v in r.items()))
        print(f"{a.effect}={a.value:g} seed {a.seed}, fold iterations {n}: held-out base {hb:.1f}, "
              f"with the effect {he:.1f}, gain {he - hb:.1f} nats (delta BIC {cand.delta_bic:.1f})", flush=True)


if __name__ == "__main__":
    main()
