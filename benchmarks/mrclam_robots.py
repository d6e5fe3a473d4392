"""Issue 7 in full: calibrate each of the five MRCLAM run-7 robots from its own log and check it against Vicon.

    nice -n 10 python benchmarks/mrclam_robots.py [--data ../shared/data/mrclam7] [--robots 1 2 3 4 5]
        [--minutes M] [--sensor-degree D] [--effect NAME]... [--cross-terms auto|on|off] [--out mrclam_runs]

Per robot: import, ``casm-graph calibrate`` (the same code path), then :func:`casm_graph.analysis.groundtruth.evaluate`.
Prints a markdown table (the README's) and writes OUT/summary.json and OUT/robotN/{model.json,report.html}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from casm_graph.analysis import groundtruth
from casm_graph.io import mrclam
from casm_graph.io.log import load
from casm_graph.models.command_model import STEP_HEADINGS
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.report import pages

ROOT = Path(__file__).resolve().parent.parent


def run_robot(data: Path, robot: int, out: Path, minutes: float | None, degree: int, effects=(),
              cross_terms: bool | str = "auto", step_heading: str = "auto") -> dict:
    bundle = out / f"robot{robot}_log"
    log, _ = mrclam.import_robot(data, robot, bundle)
    if minutes:
        from casm_graph.io.log import write
        write(log.window(log.t[0], log.t[0] + 60 * minutes), bundle)
    t0 = time.perf_counter()
    log, fit = calibrate_run.run(bundle, out / f"robot{robot}", sensor_degree=degree, effects=tuple(effects),
                                 cross_terms=cross_terms, step_heading=step_heading, force=True)
    seconds = time.perf_counter() - t0
    ev = groundtruth.evaluate(load(bundle), fit)
    pages.calibration(out / f"robot{robot}" / "report.html", log, fit, evaluation=ev)
    ev["calibrate_seconds"] = seconds
    return ev


def table(results: dict) -> str:
    head = ("| robot | min | sightings | turn map RMS (% of range) | speed map RMS (% of range) | "
            "position RMS: calibrated graph | identity-model graph | ratio | dead reckoning raw | calibrate s |\n"
            "|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for r, e in results.items():
        me, pr = e["map_error"], e["position_rms"]
        rows.append(f"| {r} | {e['minutes']:.1f} | {e['observations']} | {me['w']['rms']:.3f} rad/s "
                    f"({100 * me['w']['fraction']:.1f} %) | {1000 * me['v']['rms']:.1f} mm/s "
                    f"({100 * me['v']['fraction']:.1f} %) | {pr['calibrated_graph']:.3f} m | "
                    f"{pr['identity_graph']:.3f} m | {e['ratio_to_identity']:.2f} | "
                    f"{pr['dead_reckoning_raw']:.2f} m | {e['calibrate_seconds']:.0f} |")
    return head + "\n" + "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(mrclam.find_data()))
    p.add_argument("--robots", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    p.add_argument("--minutes", type=float, default=None, help="first M minutes only (default: whole log)")
    p.add_argument("--sensor-degree", type=int, default=3)
    p.add_argument("--effect", action="append", default=[], metavar="NAME",
                   help="calibrate with this effect (repeatable; issue 7's are lens_distortion and actuator_lag)")
    p.add_argument("--cross-terms", default="auto", choices=("auto", "on", "off"),
                   help="the turn map's term in v, as calibrate's option (default auto)")
    p.add_argument("--step-heading", default="auto", choices=("auto", *STEP_HEADINGS),
                   help="the heading a command step moves along, as calibrate's option (default auto: the middle)")
    p.add_argument("--out", default="mrclam_runs")
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for r in a.robots:
        results[r] = run_robot(Path(a.data), r, out, a.minutes, a.sensor_degree, a.effect,
                               {"on": True, "off": False}.get(a.cross_terms, "auto"), a.step_heading)
        print(table({r: results[r]}).splitlines()[-1], file=sys.stderr, flush=True)
        clean = {q: {k: v for k, v in e.items() if not k.startswith("_")} for q, e in results.items()}
        (out / "summary.json").write_text(json.dumps(clean, indent=2, default=lambda x: np.asarray(x).tolist()))
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
