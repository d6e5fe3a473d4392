"""Discovery beyond the catalog on the independent test world: proposal, fit, error against the truth.

    OPENBLAS_NUM_THREADS=1 python benchmarks/proposal.py --effects heading_speed time_speed --seeds 0 1

For each uncataloged effect and seed: an action-table log (``--kind continuous``: v,w commands) of the
independent world (tests/worlds),
calibrate, diagnose, and when the verdict is ``unexplained`` the proposal's equation; then calibrate with
the proposal and report the fitted equation, the position RMS against the truth before and after, and the
next verdict. One JSON line per log with --json.
"""
import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

import casm_graph as cg
from casm_graph.analysis.groundtruth import trajectory_rms
from casm_graph.analysis.proposal import strongest_t
from casm_graph.models.effects.proposal import equation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "worlds"))
import independent_world as W  # noqa: E402


def heading_rms(cal, log) -> float:
    d = np.angle(np.exp(1j * (cal.trajectory["theta"] - log.truth[:, 3])))
    return float(np.sqrt(np.mean(d ** 2)))


def one(effect: str, seed: int, minutes: float, kind: str = "table", cross_terms="auto",
        step_heading: str = "auto") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        W.generate(tmp, kind=kind, minutes=minutes, seed=seed, effect=None if effect == "none" else effect,
                   min_range=0.8)
        truth = json.loads((Path(tmp) / "world_truth.json").read_text())
        log = cg.load_log(tmp)
    cal = cg.calibrate(log, cross_terms=cross_terms, step_heading=step_heading)
    diag = cg.diagnose(log, cal)
    ct = cal.model.fit.get("cross_term") or {}
    row = {"effect": effect, "seed": seed, "strength": truth["strength"], "geometry": truth["geometry"],
           "turn_per_speed": ct.get("w_per_v") if ct.get("kept") else None,
           "verdict": diag.verdict, "proposal": diag.proposal.get("equation", []),
           "strongest_t": strongest_t(diag.proposal),
           "position_rms": [trajectory_rms(cal.trajectory, log.truth)], "heading_rms": [heading_rms(cal, log)]}
    if diag.proposal:
        cal2 = cg.calibrate(log, effects=[diag.proposal_effect()], cross_terms=cross_terms, step_heading=step_heading)
        after = cg.diagnose(log, cal2, before=diag)
        row.update(fitted=equation(cal2.model.effects["proposal"]), verdict_after=after.verdict)
        row["position_rms"].append(trajectory_rms(cal2.trajectory, log.truth))
        row["heading_rms"].append(heading_rms(cal2, log))
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", nargs="+", default=["heading_speed", "position_drift_speed", "time_speed", "none"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--kind", choices=("table", "continuous"), default="table")
    ap.add_argument("--cross-terms", choices=("auto", "on", "off"), default="auto",
                    help="calibrate's cross_terms (continuous logs: the turn map's term in v)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    a = ap.parse_args()
    for effect in a.effects:
        for seed in a.seeds:
            row = one(effect, seed, a.minutes, a.kind, {"on": True, "off": False}.get(a.cross_terms, "auto"),
                      a.step_heading)
            held = "" if row["turn_per_speed"] is None else f"turn map's term in v {row['turn_per_speed']:.3f}; "
            print(f"{effect} seed {seed} (s={row['strength']}): {held}{row['verdict']}; proposal {row['proposal']} "
                  f"(strongest |t| {row['strongest_t']}); "
                  f"fitted {row.get('fitted')}; position RMS {[round(x, 4) for x in row['position_rms']]}; "
                  f"heading RMS {[round(x, 4) for x in row['heading_rms']]}; "
                  f"after {row.get('verdict_after')}", flush=True)
            if a.json:
                with open(a.json, "a") as f:
                    f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
