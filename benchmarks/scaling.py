"""How each command's cost grows with the log's length (issue 25).

For every log length (``--minutes``, default 15 30 60 120) and log kind (``--kinds``: ``table`` is the
action-table Aibo log, ``floor`` the continuous v,w commands of ``--protocol floor``) the project's
simulator writes a log (``--seed``, default 5), then each command (``--commands``: ``calibrate``, and
optionally ``diagnose`` and ``uncertainty``, which start from the calibrate run) runs in its own
process of ``casm-graph``. Printed as a markdown table: wall time, peak memory (the child's maximum
resident set size, from ``os.wait4``), iterations (``fit.iterations`` of model.json, calibrate only),
the share of each progress stage (read from the tqdm bars the CLI prints on stderr, to the second),
and per kind and command the fitted exponent of cost against length (least-squares slope of log
time on log minutes: 1 is linear).

    OPENBLAS_NUM_THREADS=1 python benchmarks/scaling.py --minutes 15 30 60 120 --kinds table floor

The commands run under the interpreter running this script, so ``PYTHONPATH=/some/other/checkout``
measures another version of the package the same way. Absolute times vary with the machine and
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


def run(cmd: list[str], log_file: Path) -> dict:
    """Run ``cmd``; wall seconds, the child's peak RSS (MB), exit code and its stderr."""
    t0 = time.perf_counter()
    with open(log_file, "w") as err:
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    text = log_file.read_text(errors="replace")
    return {"seconds": wall, "peak_mb": usage.ru_maxrss / 1024.0, "status": p.returncode, "stderr": text}


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "casm_graph.cli", *args]


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
    ap.add_argument("--work", default=None, help="directory for the logs and runs (default: a temporary one)")
    ap.add_argument("--json", default=None, help="also write the measurements here")
    args = ap.parse_args(argv)

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
                r = subprocess.run(cli(*sim), capture_output=True, text=True)
                if r.returncode:
                    print(r.stderr, file=sys.stderr)
                    return 1
            run_dir = work / "runs" / tag
            for command in args.commands:
                out = run_dir / command
                if out.exists():
                    shutil.rmtree(out)
                if command == "calibrate":
                    cmd = cli("calibrate", str(log_dir), "--out", str(out))
                else:
                    cmd = cli(command, str(log_dir), "--model", str(run_dir / "calibrate" / "model.json"), "--out", str(out))
                res = run(cmd, work / f"{tag}_{command}.stderr")
                if res["status"]:
                    print(f"{' '.join(cmd)} failed (status {res['status']}):\n{res['stderr'][-2000:]}", file=sys.stderr)
                iterations = None
                if command == "calibrate" and (out / "model.json").is_file():
                    iterations = json.loads((out / "model.json").read_text())["fit"].get("iterations")
                stages = stage_seconds(res["stderr"])
                rows.append({"kind": kind, "minutes": minutes, "command": command, "seconds": res["seconds"],
                             "peak_mb": res["peak_mb"], "iterations": iterations, "stages": stages,
                             "status": res["status"]})
                print(f"{kind} {minutes:g} min {command}: {res['seconds']:.1f} s, {res['peak_mb']:.0f} MB, "
                      f"{iterations} iterations", file=sys.stderr, flush=True)

    print("| kind | minutes | command | wall s | peak MB | iterations | stage shares |")
    print("|---|---:|---|---:|---:|---:|---|")
    for r in rows:
        total = sum(r["stages"].values())
        shares = ", ".join(f"{k} {100 * v / total:.0f}%" for k, v in r["stages"].items()) if total else ""
        status = "" if r["status"] == 0 else f" (failed, status {r['status']})"
        print(f"| {r['kind']} | {r['minutes']:g} | {r['command']}{status} | {r['seconds']:.1f} | {r['peak_mb']:.0f} | "
              f"{'' if r['iterations'] is None else r['iterations']} | {shares} |")
    print()
    print("| kind | command | exponent of wall time vs minutes | longest / shortest |")
    print("|---|---|---:|---:|")
    for kind in args.kinds:
        for command in args.commands:
            sel = [r for r in rows if r["kind"] == kind and r["command"] == command and r["status"] == 0]
            if len(sel) >= 2:
                sel.sort(key=lambda r: r["minutes"])
                k = exponent([r["minutes"] for r in sel], [r["seconds"] for r in sel])
                ratio = sel[-1]["seconds"] / sel[0]["seconds"]
                print(f"| {kind} | {command} | {k:.2f} | {ratio:.1f}x for {sel[-1]['minutes'] / sel[0]['minutes']:g}x |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"\n(logs and runs in {work})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
