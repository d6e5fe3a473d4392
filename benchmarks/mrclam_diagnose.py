"""Issue 7, item 4: diagnose the MRCLAM robots' own calibrations, add the effect, check the change against Vicon.

    OPENBLAS_NUM_THREADS=1 python benchmarks/mrclam_diagnose.py [--robots 1 2 3 4 5] [--out mrclam_diag]

Per robot, through the command line's code paths: ``calibrate`` (base), ``diagnose`` (residual
structure and the candidates a continuous log can take), ``calibrate --effect E...`` with every
candidate BIC supports strongly (delta BIC <= -10), and :func:`casm_graph.analysis.groundtruth.evaluate` on
both fits. Prints one row per robot (the README's table) with the three strongest residual
structures of each base model and the position RMS over the identity-model graph's (the uncalibrated
models, no effects; the issue's target is at most 0.5); writes OUT/summary.json.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from casm_graph.analysis import groundtruth
from casm_graph.analysis.diagnosis import BIC_SUPPORT
from casm_graph.io import mrclam
from casm_graph.io.log import load
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.pipeline import diagnose as diagnose_run


def run_robot(data: Path, robot: int, out: Path, step_heading: str = "auto") -> dict:
    bundle = out / f"robot{robot}_log"
    mrclam.import_robot(data, robot, bundle)
    _, base = calibrate_run.run(bundle, out / f"robot{robot}", step_heading=step_heading)
    diag = diagnose_run.run(bundle, out / f"robot{robot}" / "model.json", out / f"robot{robot}_diag")
    added = [c.effect for c in diag.candidates if c.delta_bic <= BIC_SUPPORT]
    _, after = (calibrate_run.run(bundle, out / f"robot{robot}_effects", effects=added, step_heading=step_heading)
                if added else (None, base))
    log = load(bundle)
    ev = {name: groundtruth.evaluate(log, f) for name, f in (("base", base), ("after", after))}
    return {"verdict": diag.verdict, "summary": diag.words,
            "structure": [{k: s[k] for k in ("channel", "name", "kind", "strength")} for s in diag.structure[:3]],
            "candidates": [c.to_json() for c in diag.candidates], "added": added,
            "fitted": after.model.effects,
            **{name: {"map_error": {k: e["map_error"][k]["fraction"] for k in ("v", "w")},
                      "position_rms": e["position_rms"]["calibrated_graph"],
                      "identity_graph": e["position_rms"]["identity_graph"],
                      "log_likelihood": f.log_likelihood}
               for (name, e), f in zip(ev.items(), (base, after))}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(mrclam.find_data()))
    p.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    p.add_argument("--out", default="mrclam_diag")
    p.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                    help="the heading a command step moves along, as calibrate's option (default auto)")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {}
    print("| robot | verdict | strongest residual structure (omega squared) | candidates: delta BIC (fitted) | "
          "added | turn map % base -> after | speed map % base -> after | position RMS m base -> after | "
          "identity-model graph m | ratio base -> after |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in a.robots:
        e = res[r] = run_robot(Path(a.data), r, out, a.step_heading)
        s = "; ".join(f"{x['channel']} {x['kind']} vs {x['name']} {x['strength']:.3f}" for x in e["structure"]) or "none"
        c = "; ".join(f"{x['effect']} {x['delta_bic']:.0f} ({', '.join(f'{k} {v:.3g}' for k, v in x['parameters'].items() if isinstance(v, float))})"
                      for x in e["candidates"])
        b, g = e["base"], e["after"]
        print(f"| {r} | {e['verdict']} | {s} | {c} | {', '.join(e['added']) or 'none'} | "
              f"{100 * b['map_error']['w']:.1f} -> {100 * g['map_error']['w']:.1f} | "
              f"{100 * b['map_error']['v']:.1f} -> {100 * g['map_error']['v']:.1f} | "
              f"{b['position_rms']:.3f} -> {g['position_rms']:.3f} | {b['identity_graph']:.3f} | "
              f"{b['position_rms'] / b['identity_graph']:.2f} -> {g['position_rms'] / b['identity_graph']:.2f} |",
              flush=True)
    (out / "summary.json").write_text(json.dumps(res, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
