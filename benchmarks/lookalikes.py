"""Look-alike groups on the independent world: which candidates change the predicted sightings alike.

For each (effect, seed, nearest sighting) a six-minute table log of ``tests/worlds/independent_world.py``
is calibrated and diagnosed (every candidate); for each supported runner-up the row gives its delta BIC beside
the verdict's and the shares of each fit's change to the base's predicted sightings that the other reproduces
(:func:`casm_graph.analysis.diagnosis.reproduced_share`), and the look-alike group the diagnosis reports.

    OPENBLAS_NUM_THREADS=1 python benchmarks/lookalikes.py --effects camera_latency actuator_lag --seeds 0 1 2 3 \\
        --min-range 0.8 --out lookalikes.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1]))   # tests.worlds; PYTHONPATH still picks casm_graph

import casm_graph as cg  # noqa: E402
from casm_graph.analysis.diagnosis import DEFAULTS, predicted_sightings, reproduced_share  # noqa: E402
from casm_graph.fit import effect_fit  # noqa: E402
from casm_graph.models.effects import of_model  # noqa: E402
from tests.worlds.independent_world import generate  # noqa: E402


def one(effect: str, seed: int, min_range: float, minutes: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "log"
        generate(d, kind="table", minutes=minutes, seed=seed, effect=None if effect == "none" else effect,
                 min_range=min_range)
        log = cg.load_log(d)
        cal = cg.calibrate(log)
        diag = cg.diagnose(log, cal)
        o = DEFAULTS       # the base the diagnosis scores against, rebuilt the same way (deterministic)
        present = of_model(cal.model.effects, ())
        refit = effect_fit.fit(log, cal.model, cal.fit.poses, present, rounds=o.candidate_rounds,
                               iterations=o.candidate_iterations)
        base = effect_fit.fit(log, refit.model, refit.poses, present, rounds=o.candidate_rounds,
                              iterations=o.candidate_iterations)
        bp = predicted_sightings(base.problem, base.state)
        best = next((c for c in diag.candidates if c.effect == diag.verdict), None)
        rivals = []
        for c in diag.candidates:
            if best is None or c is best or c.delta_bic > o.bic_support or c.prediction is None:
                continue
            rivals.append({"effect": c.effect, "delta_bic": round(c.delta_bic, 1),
                           "its_change_reproduced": round(reproduced_share(bp, c.prediction, best.prediction), 3),
                           "reproduces_verdicts": round(reproduced_share(bp, best.prediction, c.prediction), 3)})
        return {"effect": effect, "seed": seed, "min_range": min_range, "verdict": diag.verdict,
                "verdict_delta_bic": None if best is None else round(best.delta_bic, 1), "rivals": rivals,
                "lookalikes": [g["effects"] for g in diag.lookalikes]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effects", nargs="+", default=["camera_latency", "actuator_lag"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    ap.add_argument("--min-range", type=float, default=0.8)
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--out", required=True, help="one JSON line per log, appended")
    a = ap.parse_args(argv)
    with open(a.out, "a") as f:
        for effect in a.effects:
            for seed in a.seeds:
                r = one(effect, seed, a.min_range, a.minutes)
                f.write(json.dumps(r) + "\n")
                f.flush()
                print(f"{effect} seed {seed}: {r['verdict']} ({r['verdict_delta_bic']}); look-alikes "
                      f"{r['lookalikes']}; " + "; ".join(
                          f"{x['effect']} {x['delta_bic']} (shares {x['its_change_reproduced']}, "
                          f"{x['reproduces_verdicts']})" for x in r["rivals"]), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
