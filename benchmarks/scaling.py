"""How each command's cost grows with the log's length (issue 25).

For every log length (``--minutes``, default 15 30 60 120) and log kind (``--kinds``: ``table`` is the
action-table Aibo log, ``floor`` the continuous v,w commands of ``--protocol floor``) the project's
simulator writes a log (``--seed``, default 5), then each command (``--commands``: ``calibrate``, and
optionally ``diagnose`` and ``uncertainty``, which start from the calibrate run, so it always runs first) runs in
its own process of ``casm-graph``. Printed as a markdown table: wall time, peak memory (the child's maximum
resident set size, from ``os.wait4``), iterations (``fit.iterations`` of model.json, calibrate only),
the share of each progress stage (read from the tqdm bars the CLI prints on stderr, to the second),
and per kind and command the fitted exponent of cost against length (least-squares slope of log
time on log minutes: 1 is linear), of wall time and of the child's CPU time (which load on a shared
machine moves less); for ``uncertainty`` also the sampler's length (steps, set by the autocorrelation
time) and its CPU seconds per likelihood evaluation, whose exponent is the cost per sample.

    OPENBLAS_NUM_THREADS=1 python benchmarks/scaling.py --minutes 15 30 60 120 --kinds table floor

The commands run under the interpreter running this script, so ``PYTHONPATH=/some/other/checkout``
measures another version of the package the same way, and ``--versions before=/tmp/base after=.``
measures several side by side in one run (each command on each log by each version in turn, each
version's diagnose and uncertainty from its own calibrate; a path is put first on the children's
PYTHONPATH, ``.`` leaves it as it is). Each calibrate is checked against the simulator's truth
(action table: RMS error of the velocity table and of the sensor curve; floor: trajectory position
RMS) and, with several versions, against the first version's (largest relative difference of the
velocities, sensor polynomial, velocity std and pose std). Absolute times vary with the machine and
its load; compare runs made side by side.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from casm_graph.models.model import Model
from casm_graph.sim.aibo import true_reading

PROTOCOL = {"table": "aibo", "floor": "floor"}
# a tqdm bar as the CLI draws it: "<stage>: ... [<elapsed>]" (elapsed m:ss or h:mm:ss)
BAR = re.compile(r"^\s*([^:\r\n]+?): (?:.*\|.*)?\[(\d+(?::\d\d){1,2})\]")


def _seconds(clock: str) -> int:
    s = 0
    for part in clock.split(":"):
        s = 60 * s + int(part)
    return s


def stage_seconds(stderr: str) -> dict[str, int]:
    """Seconds shown by each progress bar when it last redrew (a stage whose clock restarts, run again, is summed)."""
    done: dict[str, int] = {}
    now: dict[str, int] = {}
    for frame in re.split(r"[\r\n]", stderr):
        m = BAR.match(frame)
        if m:
            name, sec = m.group(1).strip(), _seconds(m.group(2))
            if sec < now.get(name, 0):
                done[name] = done.get(name, 0) + now[name]
            now[name] = sec
    return {k: done.get(k, 0) + v for k, v in now.items()}


def run(cmd: list[str], log_file: Path, pythonpath: str = ".") -> dict:
    """Run ``cmd`` (``pythonpath`` first on its PYTHONPATH, ``.``: as inherited); wall seconds, the child's
    CPU seconds (user + system: steadier than wall time on a loaded machine), peak RSS (MB), exit code and
    its stderr."""
    env = {**os.environ, "PYTHONSAFEPATH": "1"}      # not the working directory's package ahead of PYTHONPATH
    if pythonpath != ".":
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(Path(pythonpath).resolve()), env.get("PYTHONPATH")) if p)
    t0 = time.perf_counter()
    with open(log_file, "w") as err:
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    text = log_file.read_text(errors="replace")
    return {"seconds": wall, "cpu": usage.ru_utime + usage.ru_stime, "peak_mb": usage.ru_maxrss / 1024.0,
            "status": p.returncode, "stderr": text}


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "casm_graph.cli", *args]


def accuracy(kind: str, log_dir: Path, run_dir: Path) -> str:
    """The calibration's error against the simulator's truth, as one table cell."""
    model = Model.load(run_dir / "model.json")
    if kind == "table":
        truth = json.loads((log_dir / "truth_model.json").read_text())
        tv = np.array([truth["action_model"]["velocities"][str(a)] for a in model.action_ids])
        rms = np.sqrt(np.mean((model.velocities - tv) ** 2, axis=0))
        d = np.linspace(*model.distance_range, 200)
        curve = np.sqrt(np.mean((model.reading(d) - true_reading(truth, d)) ** 2))
        return f"vx {1000 * rms[0]:.4f}, vy {1000 * rms[1]:.4f} mm/s, w {rms[2]:.6f} rad/s, curve {curve:.5f} px"
    truth = np.loadtxt(log_dir / "truth.csv", delimiter=",", skiprows=1)
    traj = np.loadtxt(run_dir / "trajectory.csv", delimiter=",", skiprows=1)
    return f"position RMS {np.sqrt(np.mean(np.sum((traj[:, 1:3] - truth[:, 1:3]) ** 2, axis=1))):.5f} m"


def difference(a: Path, b: Path) -> str:
    """Largest relative difference of two calibrations of one log (velocities or command map, sensor
    polynomial, velocity or command-map std, pose std), as one table cell."""
    ja, jb = (json.loads((d / "model.json").read_text()) for d in (a, b))
    ta, tb = (np.loadtxt(d / "trajectory.csv", delimiter=",", skiprows=1) for d in (a, b))

    def flat(j: dict, key: str) -> np.ndarray:
        x = j["action_model"].get(key) or []
        parts = [x[k] for k in sorted(x)] if isinstance(x, dict) else [x]
        return np.concatenate([np.ravel(np.asarray(v, float)) for v in parts]) if parts else np.zeros(0)

    def rel(x, y) -> float:
        x, y = np.asarray(x, float), np.asarray(y, float)
        if x.shape != y.shape:
            return float("inf")
        return float(np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-300), initial=0.0))

    key = "velocities" if "velocities" in ja["action_model"] else "coefficients"
    parts = {"model": max(rel(flat(ja, key), flat(jb, key)),
                          rel(ja["sensor_model"]["reading_poly"], jb["sensor_model"]["reading_poly"])),
             "model std": rel(flat(ja, "std"), flat(jb, "std")), "pose std": rel(ta[:, 4:], tb[:, 4:])}
    return ", ".join(f"{k} {v:.1e}" for k, v in parts.items())


def exponent(minutes: list[float], seconds: list[float]) -> float:
    """Least-squares slope of log(seconds) on log(minutes)."""
    if len(minutes) < 2:
        return float("nan")
    return float(np.polyfit(np.log(minutes), np.log(seconds), 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[15, 30, 60, 120])
    ap.add_argument("--kinds", nargs="+", default=["table", "floor"], choices=sorted(PROTOCOL))
    ap.add_argument("--commands", nargs="+", default=["calibrate"], choices=["calibrate", "diagnose", "uncertainty"])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--versions", nargs="+", default=["."], metavar="LABEL=PATH",
                    help="versions to measure side by side: a checkout put first on PYTHONPATH (.: as inherited)")
    ap.add_argument("--work", default=None, help="directory for the logs and runs (default: a temporary one)")
    ap.add_argument("--json", default=None, help="also write the measurements here")
    args = ap.parse_args(argv)
    commands = ["calibrate"] + [c for c in args.commands if c != "calibrate"]   # the others start from its run
    versions = [tuple(v.split("=", 1)) if "=" in v else (v, v) for v in args.versions]

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="casm_scaling_"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for kind in args.kinds:
        for minutes in args.minutes:
            tag = f"{kind}_{minutes:g}min_seed{args.seed}"
            log_dir = work / "logs" / tag
            if not (log_dir / "commands.csv").is_file():
                sim = ["simulate", str(log_dir), "--minutes", f"{minutes:g}", "--seed", str(args.seed),
                       "--protocol", PROTOCOL[kind]]
                r = subprocess.run(cli(*sim), check=False, capture_output=True, text=True)
                if r.returncode:
                    print(r.stderr, file=sys.stderr)
                    return 1
            for command in commands:
                for label, path in versions:
                    run_dir = work / "runs" / label / tag
                    out = run_dir / command
                    if out.exists():
                        shutil.rmtree(out)
                    if command == "calibrate":
                        cmd = cli("calibrate", str(log_dir), "--out", str(out))
                    else:
                        cmd = cli(command, str(log_dir), "--model", str(run_dir / "calibrate" / "model.json"),
                                  "--out", str(out))
                    res = run(cmd, work / f"{label}_{tag}_{command}.stderr", path)
                    if res["status"]:
                        print(f"{' '.join(cmd)} failed (status {res['status']}):\n{res['stderr'][-2000:]}",
                              file=sys.stderr)
                    iterations, check, same, sampler = None, "", "", None
                    if command == "uncertainty" and (out / "posterior.json").is_file():
                        post = json.loads((out / "posterior.json").read_text())
                        sampler = {"steps": post["sampler"]["steps"], "walkers": post["sampler"]["walkers"],
                                   "evaluations": post["likelihood"]["evaluations"],
                                   "cpu_per_evaluation": post["likelihood"]["cpu_seconds_per_evaluation"],
                                   "tau": max(post["sampler"]["autocorr_time"].values())}
                    if command == "calibrate" and (out / "model.json").is_file():
                        iterations = json.loads((out / "model.json").read_text())["fit"].get("iterations")
                        check = accuracy(kind, log_dir, out)
                        first = work / "runs" / versions[0][0] / tag / "calibrate"
                        if label != versions[0][0] and (first / "model.json").is_file():
                            same = difference(out, first)
                    rows.append({"version": label, "kind": kind, "minutes": minutes, "command": command,
                                 "seconds": res["seconds"], "cpu": res["cpu"], "peak_mb": res["peak_mb"], "iterations": iterations,
                                 "stages": stage_seconds(res["stderr"]), "status": res["status"],
                                 "truth": check, "vs_first": same, "sampler": sampler})
                    print(f"{label} {kind} {minutes:g} min {command}: {res['seconds']:.1f} s ({res['cpu']:.1f} CPU s), "
                          f"{res['peak_mb']:.0f} MB, "
                          f"{iterations} iterations", file=sys.stderr, flush=True)

    print("| version | kind | minutes | command | wall s | CPU s | peak MB | iterations | stage shares |")
    print("|---|---|---:|---|---:|---:|---:|---:|---|")
    for r in rows:
        total = sum(r["stages"].values())
        shares = ", ".join(f"{k} {100 * v / total:.0f}%" for k, v in r["stages"].items()) if total else ""
        status = "" if r["status"] == 0 else f" (failed, status {r['status']})"
        print(f"| {r['version']} | {r['kind']} | {r['minutes']:g} | {r['command']}{status} | {r['seconds']:.1f} | "
              f"{r['cpu']:.1f} | "
              f"{r['peak_mb']:.0f} | {'' if r['iterations'] is None else r['iterations']} | {shares} |")
    print()
    head = "| version | kind | minutes | against the truth |" + (f" largest relative difference from {versions[0][0]} |"
                                                             if len(versions) > 1 else "")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        if r["truth"]:
            print(f"| {r['version']} | {r['kind']} | {r['minutes']:g} | {r['truth']} |"
                  + (f" {r['vs_first'] or '-'} |" if len(versions) > 1 else ""))
    print()
    samplers = [r for r in rows if r["sampler"]]
    if samplers:
        print("| version | kind | minutes | sampler steps x walkers | max tau | CPU s per evaluation |")
        print("|---|---|---:|---:|---:|---:|")
        for r in samplers:
            sp = r["sampler"]
            print(f"| {r['version']} | {r['kind']} | {r['minutes']:g} | {sp['steps']} x {sp['walkers']} | "
                  f"{sp['tau']:.1f} | {sp['cpu_per_evaluation']:.4f} |")
        print()
    print("| version | kind | command | exponent of wall time | of CPU time | of CPU per evaluation | "
          "longest / shortest (wall) |")
    print("|---|---|---|---:|---:|---:|---:|")
    for label, _ in versions:
        for kind in args.kinds:
            for command in commands:
                sel = [r for r in rows if r["version"] == label and r["kind"] == kind and r["command"] == command
                       and r["status"] == 0]
                if len(sel) >= 2:
                    sel.sort(key=lambda r: r["minutes"])
                    mins = [r["minutes"] for r in sel]
                    k = exponent(mins, [r["seconds"] for r in sel])
                    kc = exponent(mins, [r["cpu"] for r in sel])
                    ke = (f"{exponent(mins, [r['sampler']['cpu_per_evaluation'] for r in sel]):.2f}"
                          if all(r["sampler"] for r in sel) else "")
                    ratio = sel[-1]["seconds"] / sel[0]["seconds"]
                    print(f"| {label} | {kind} | {command} | {k:.2f} | {kc:.2f} | {ke} | "
                          f"{ratio:.1f}x for {sel[-1]['minutes'] / sel[0]['minutes']:g}x |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"\n(logs and runs in {work})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
