"""How well the score test predicts each candidate's fitted gain, and what screening by it costs in verdicts.

For each world (the project's Aibo simulator and the independent table world, an effect hidden or none) the base
model is calibrated and every candidate member is both fitted (as ``diagnose`` with ``screen_share=0``) and
scored by the score test (``casm_graph.analysis.score_test``). One JSON line per world: per member the predicted
and the fitted log-likelihood gain and BIC penalty. The table says how many members a screen at
``--share`` would leave unfitted and whether any of them had a fitted delta BIC below zero (a candidate that
could have mattered).

    OPENBLAS_NUM_THREADS=1 python benchmarks/score_screen.py --minutes 6 --seeds 0 --out screen.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from multiprocessing import Pool
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                                                   # noqa: E402
from casm_graph.analysis import diagnosis as D                            # noqa: E402
from casm_graph.analysis.candidates import table as TB                    # noqa: E402
from casm_graph.analysis.score_test import predicted_floor, predicted_gain  # noqa: E402
from casm_graph.fit import effect_fit                                     # noqa: E402
from casm_graph.graph.augmented import begin, instantiate                 # noqa: E402
from casm_graph.models.effects import REGISTRY, of_model, spec            # noqa: E402
from casm_graph.sim.aibo import SimConfig, simulate, write                # noqa: E402
from tests.worlds.independent_world import generate                       # noqa: E402

OWN = {"actuator_lag": 0.3, "battery_fade": 0.02, "surface_friction": 0.15, "camera_latency": 0.1,
       "lens_distortion": 0.3, "landmark_offset": 0.2, "none": 0.0}
INDEPENDENT = ("actuator_lag", "camera_latency", "surface_friction", "battery_fade", "none")


def world(args) -> dict:
    """Every member of every applicable candidate on one world: predicted and fitted gains."""
    source, effect, seed, minutes = args
    with tempfile.TemporaryDirectory() as w, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path = Path(w) / "log"
        if source == "own":
            log, truth = simulate(SimConfig(minutes=minutes, seed=seed,
                                            effects={} if effect == "none" else {effect: OWN[effect]}))
            write(log, truth, path)
        else:
            generate(path, kind="table", minutes=minutes, seed=seed, effect=None if effect == "none" else effect,
                     min_range=0.8)
        log = cg.load_log(path)
        cal = cg.calibrate(log, seed=seed)
        o = D.DiagnoseOptions(screen_share=0.0)
        model = cal.model.with_(velocities=cal.model.velocities[np.searchsorted(cal.model.action_ids, log.action_ids)],
                                action_ids=log.action_ids, velocity_std=None)
        poses = np.column_stack([cal.trajectory[k] for k in ("x", "y", "theta")])
        present = of_model(model.effects)
        refit = effect_fit.fit(log, model, poses, present, rounds=o.candidate_rounds,
                               iterations=o.candidate_iterations)
        base = effect_fit.fit(log, refit.model, refit.poses, present, rounds=o.candidate_rounds,
                              iterations=o.candidate_iterations)
        floor = predicted_floor(base.problem, base.state)
        rows = []
        for cls in sorted(REGISTRY.values(), key=lambda c: c.name):
            if cls(log).applicable(log):
                continue
            for m in D.family_members(cls):
                eff = instantiate([m], log)[0]
                begin([eff], refit.model, refit.poses)          # a start from the log, as the diagnosis gives it
                t0 = time.perf_counter()
                gain = predicted_gain(log, base, eff, floor)
                t_screen = time.perf_counter() - t0
                c, _, _ = TB.fit_candidate(log, refit, base, m, o)
                rows.append({"member": spec(m), "k": eff.free_parameters(),
                             "penalty": float(eff.free_parameters() * np.log(TB.n_data(log))),
                             "predicted_gain": gain, "fitted_gain": c.delta_log_likelihood,
                             "delta_bic": c.delta_bic, "seconds_screen": t_screen, "seconds_fit": c.seconds})
    return {"source": source, "effect": effect, "seed": seed, "minutes": minutes, "members": rows}


def table(rows: list[dict], share: float) -> None:
    n = screened = missed = 0
    t_fit = t_kept = 0.0
    for r in rows:
        for m in r["members"]:
            n += 1
            t_fit += m["seconds_fit"]
            if m["predicted_gain"] is None or 2 * m["predicted_gain"] >= share * m["penalty"]:
                t_kept += m["seconds_fit"] + m["seconds_screen"]
                continue
            t_kept += m["seconds_screen"]
            screened += 1
            if m["delta_bic"] < 0:
                missed += 1
                print(f"  would miss: {r['source']} {r['effect']} seed {r['seed']} {m['member']}: predicted gain "
                      f"{m['predicted_gain']:.1f}, fitted {m['fitted_gain']:.1f}, delta BIC {m['delta_bic']:.1f}")
    print(f"share {share:g}: {screened} of {n} members screened out, {missed} of them with a fitted delta BIC < 0; "
          f"candidate time {t_kept:.0f} s of {t_fit:.0f} s ({t_kept / max(t_fit, 1e-9):.2f})")
    for r in rows:
        print(f"{r['source']:12s} {r['effect']:18s} seed {r['seed']}: " + ", ".join(
            f"{m['member']} {m['predicted_gain'] if m['predicted_gain'] is None else round(m['predicted_gain'], 1)}"
            f"/{m['fitted_gain']:.1f}" for m in r["members"]))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--sources", nargs="+", default=["own", "independent"])
    ap.add_argument("--share", type=float, nargs="+", default=[D.DEFAULTS.screen_share])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="screen.jsonl")
    ap.add_argument("--table", nargs="+", metavar="JSONL", help="only print the table of earlier runs' JSON lines")
    a = ap.parse_args()
    if a.table:
        rows = [json.loads(line) for p in a.table for line in open(p) if line.strip()]
    else:
        jobs = [(s, e, seed, a.minutes) for s in a.sources for e in (OWN if s == "own" else INDEPENDENT)
                for seed in a.seeds]
        rows = []
        with Pool(a.workers) as pool, open(a.out, "a") as f:
            for r in pool.imap_unordered(world, jobs):
                f.write(json.dumps(r) + "\n")
                f.flush()
                rows.append(r)
    for s in a.share:
        table(rows, s)


if __name__ == "__main__":
    main()
