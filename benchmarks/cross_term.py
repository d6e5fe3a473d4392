"""The turn map's term in v (``cross_terms``): calibrated off and auto side by side on the wheel world, the
project's floors and MRCLAM run 7.

    OPENBLAS_NUM_THREADS=1 python benchmarks/cross_term.py --wheel-seeds 0 1 2 3 --floor-seeds 0 1 2 --mrclam 1 2 3 4 5
    OPENBLAS_NUM_THREADS=1 python benchmarks/cross_term.py --wheel-seeds --independent none actuator_lag ... \
        --independent-seeds 6 7 8 9 10 11 12 13 --minutes 4

Wheel world (tests/worlds/wheel_world.py, six minutes, 0.002 s wheel response): the true coupling is
``world_truth.json``'s ``linear_map_no_saturation.w_from_v``; the maps are scored against the wheel physics'
velocities over the commands run (% of the true range). Floors and MRCLAM have no coupling in their truth to
compare: the rows say whether the term was kept and how far the calibration moved (MRCLAM: position RMS against
Vicon). ``--independent EFFECT...`` calibrates the independent world's continuous robot with each hidden effect
(sightings from 0.3 m, as benchmarks/independent_world.py makes them) with ``auto`` only, and says whether the
term was kept: where it was not, the calibration, the diagnosis and everything after are those without it.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import casm_graph as cg                                    # noqa: E402
from casm_graph.io import mrclam                           # noqa: E402
from casm_graph.sim.floor import FloorConfig               # noqa: E402
from casm_graph.sim.floor import simulate as simulate_floor   # noqa: E402
from tests.worlds.independent_world import generate        # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
WHEEL = ROOT / "tests" / "worlds" / "wheel_world.py"


def calibrate(log, cross, heading: str = "auto"):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cg.calibrate(log, cross_terms=cross, step_heading=heading)


def position_rms(cal, t, x, y) -> float:
    tr = cal.trajectory
    return float(np.sqrt(np.mean((tr["x"] - np.interp(tr["t"], t, x)) ** 2 + (tr["y"] - np.interp(tr["t"], t, y)) ** 2)))


def term(cal) -> str:
    ct = cal.model.fit.get("cross_term") or {}
    if not ct:
        return "-"
    sd = ct.get("w_per_v_std")
    return (f"{ct['w_per_v']:+.3f}" + (f" +- {sd:.3f}" if sd is not None else "") + f", delta BIC {ct['delta_bic']:,.0f}, "
            + ("kept" if ct["kept"] else "not kept"))


def wheel(seed: int, minutes: float, work: Path, heading: str = "auto") -> str:
    path = work / f"wheel_{seed}"
    subprocess.run([sys.executable, str(WHEEL), str(path), "--minutes", str(minutes), "--seed", str(seed),
                    "--base-tau", "0.002"], check=True, capture_output=True)
    truth = json.loads((path / "world_truth.json").read_text())["linear_map_no_saturation"]["w_from_v"]
    log = cg.load_log(path)
    cmd = np.genfromtxt(path / "cmd_truth.csv", delimiter=",", names=True)
    tr = np.genfromtxt(path / "truth.csv", delimiter=",", names=True)
    controls, true = np.column_stack([cmd["v"], cmd["w"]]), np.column_stack([cmd["v_true"], cmd["w_true"]])
    cells = []
    for cross in (False, "auto"):
        cal = calibrate(log, cross, heading)
        err = np.sqrt(np.mean((cal.model.command.velocities(controls)[:, [0, 2]] - true) ** 2, axis=0)) / np.ptp(true, axis=0)
        cells.append((cal, 100 * err[1], position_rms(cal, tr["t"], tr["x"], tr["y"])))
    (_, t0, p0), (auto, t1, p1) = cells
    return f"| wheel world, seed {seed} | {truth:+.3f} | {term(auto)} | {t0:.2f} -> {t1:.2f} | {p0:.4f} -> {p1:.4f} |"


def floor(seed: int, minutes: float, config: dict, heading: str = "auto") -> str:
    log, _ = simulate_floor(FloorConfig(minutes=minutes, seed=seed, **config))
    off, auto = calibrate(log, False, heading), calibrate(log, "auto", heading)
    moved = np.max(np.abs(auto.trajectory["x"] - off.trajectory["x"]))
    said = "".join(f", {k} {v:g}" for k, v in config.items())
    return f"| floor, seed {seed}{said} | 0 | {term(auto)} | - | largest x change {moved:.4f} m |"


def robot(r: int, work: Path, heading: str = "auto") -> str:
    mrclam.import_robot(mrclam.find_data(), r, work / f"robot{r}")
    log = cg.load_log(work / f"robot{r}")
    gt = np.genfromtxt(work / f"robot{r}" / "truth.csv", delimiter=",", names=True)
    off, auto = calibrate(log, False, heading), calibrate(log, "auto", heading)
    p0, p1 = (position_rms(c, gt["t"], gt["x"], gt["y"]) for c in (off, auto))
    return f"| MRCLAM robot {r} | ? | {term(auto)} | - | {p0:.3f} -> {p1:.3f} |"


def independent(effect: str, seed: int, minutes: float, work: Path, strength: float | None = None,
                heading: str = "auto") -> str:
    truth = generate(work / f"ind_{effect}_{seed}", kind="continuous", minutes=minutes, seed=seed,
                     effect=None if effect == "none" else effect, min_range=0.3, strength=strength)
    auto = calibrate(cg.load_log(work / f"ind_{effect}_{seed}"), "auto", heading)
    gain = (truth.get("geometry") or {}).get("gain", 0.0) if effect == "speed_turn" else 0.0
    return f"| independent continuous, {effect}, seed {seed} | {gain:+.3f} | {term(auto)} | - | - |"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--wheel-seeds", type=int, nargs="*", default=[0, 1, 2, 3])
    p.add_argument("--floor-seeds", type=int, nargs="*", default=[])
    p.add_argument("--floor-config", nargs="*", default=[], metavar="KEY=VALUE",
                   help="FloorConfig fields for the floors (benchmarks/continuous_effects.py: dt=0.1 actuator_lag=0.3)")
    p.add_argument("--mrclam", type=int, nargs="*", default=[])
    p.add_argument("--independent", nargs="*", default=[], metavar="EFFECT")
    p.add_argument("--independent-seeds", type=int, nargs="*", default=[0])
    p.add_argument("--strength", type=float, default=None, help="the independent world's effect strength "
                   "(default its own draw; benchmarks/hooked_effects.py's battery fade is 0.04)")
    p.add_argument("--minutes", type=float, default=6.0)
    p.add_argument("--step-heading", default="auto", choices=("auto", "start", "middle"),
                   help="the heading a command step moves along, as calibrate's option (default auto)")
    a = p.parse_args(argv)
    print("| log | true turn per forward speed, rad/s per m/s | fitted (auto), delta BIC | turn map % off -> auto | "
          "position RMS m off -> auto |\n|---|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for s in a.wheel_seeds:
            print(wheel(s, a.minutes, work, a.step_heading), flush=True)
        config = {k: float(v) for k, v in (kv.split("=", 1) for kv in a.floor_config)}
        for s in a.floor_seeds:
            print(floor(s, a.minutes, config, a.step_heading), flush=True)
        for r in a.mrclam:
            print(robot(r, work, a.step_heading), flush=True)
        for e in a.independent:
            for s in a.independent_seeds:
                print(independent(e, s, a.minutes, work, a.strength, a.step_heading), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
