"""Effects through their hooks on continuous-command logs of the independent world: named, fitted, explained.

For each hidden effect and seed: calibrate without it, diagnose (verdict, best candidate), add what the
diagnosis names (the catalog effect, or its proposal for an unexplained verdict), calibrate again and
diagnose once more (``none``: an effect-free log, for false alarms). Prints one row per log: verdict, fitted value against the truth, position RMS against
the truth before and after, the verdict after, and the time of diagnose over calibrate.

    python benchmarks/hooked_effects.py --effects battery_fade camera_latency landmark_offset heading_speed \
        --seeds 0 --minutes 4
"""
import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import casm_graph as cg  # noqa: E402
from casm_graph.analysis.groundtruth import trajectory_rms  # noqa: E402
from tests.worlds.independent_world import generate  # noqa: E402

STRENGTH = {"battery_fade": 0.04}        # else the world's own draw from its moderate range


def one(effect: str, seed: int, minutes: float, step_heading: str = "auto") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "log"
        generate(d, kind="continuous", minutes=minutes, seed=seed, effect=None if effect == "none" else effect,
                 strength=STRENGTH.get(effect))
        truth = json.loads((d / "world_truth.json").read_text())
        log = cg.load_log(d)
        t = time.perf_counter()
        cal = cg.calibrate(log, step_heading=step_heading)
        tc = time.perf_counter() - t
        t = time.perf_counter()
        diag = cg.diagnose(log, cal)
        td = time.perf_counter() - t
        row = {"effect": effect, "seed": seed, "strength": truth.get("strength"), "geometry": truth.get("geometry"),
               "verdict": diag.verdict, "lookalikes": [g["effects"] for g in diag.lookalikes],
               "best": diag.candidates[0].effect if diag.candidates else None,
               "best_delta_bic": diag.candidates[0].delta_bic if diag.candidates else None,
               "position_rms": [trajectory_rms(cal.trajectory, log.truth)], "diagnose_over_calibrate": td / tc}
        add = (diag.proposal_effect() if diag.proposal else
               diag.to_add() if diag.verdict != "none" and not diag.verdict.startswith("unexplained") else None)
        if add is not None:
            cal2 = cg.calibrate(log, effects=[add], step_heading=step_heading)
            name = add.partition(":")[0] if isinstance(add, str) else add.name
            after = cg.diagnose(log, cal2, before=diag)
            row.update(added=name, fitted=cal2.model.effects.get(name),
                       fitted_std=cal2.model.fit.get("effects_std", {}).get(name),
                       verdict_after=after.verdict, lookalikes_after=[g["effects"] for g in after.lookalikes])
            row["position_rms"].append(trajectory_rms(cal2.trajectory, log.truth))
        return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--effects", nargs="+", default=["battery_fade", "camera_latency", "landmark_offset",
                                                     "heading_speed"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--minutes", type=float, default=4.0)
    ap.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    args = ap.parse_args()
    for effect in args.effects:
        for seed in args.seeds:
            print(json.dumps(one(effect, seed, args.minutes, args.step_heading), default=float), flush=True)


if __name__ == "__main__":
    main()
