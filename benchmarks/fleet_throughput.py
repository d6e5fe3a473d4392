"""Fleet throughput on Dask: logs per minute with 1 and with 2 workers, the cost per log, and the law for N machines.

    OPENBLAS_NUM_THREADS=1 python benchmarks/fleet_throughput.py --logs 8 --minutes 3

Simulates ``--logs`` aibo logs once (one robot each, no wear), then runs ``calibrate_fleet`` on a local
cluster of each ``--workers`` count (single-threaded processes) into its own output, and measures

* wall time of the whole fleet run (cluster start, calibrations, drift, fleet.csv/json, report.html);
* cost per log: seconds one worker spends on a log (each row's ``seconds``: load, calibrate, save) and
  the CPU seconds it used (``cpu_seconds``: what a log costs on a core of its own, whatever else runs);
* the scheduler's per-task overhead: wall time per no-op task over many, on the same kind of cluster;
* the cluster's start-up and the fleet's fixed tail (drift and report), by difference.

The law for a cluster of N machines with c single-threaded workers each:
throughput ~ min(N c / cost, 1 / overhead) logs per second, plus the fixed start-up and tail per run.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from casm_graph.pipeline.fleet import calibrate_fleet, client_for
from casm_graph.sim.fleet import simulate_fleet


def overhead(workers: int, tasks: int = 400) -> tuple[float, float]:
    """(cluster start-up s, scheduler seconds per no-op task) on a local cluster of ``workers``."""
    t0 = time.perf_counter()
    with client_for(None, workers) as client:
        t1 = time.perf_counter()
        client.gather(client.map(abs, range(-20, 0), pure=False))          # warm up
        t2 = time.perf_counter()
        client.gather(client.map(abs, range(-tasks, 0), pure=False))
        t3 = time.perf_counter()
    return t1 - t0, (t3 - t2) / tasks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=8)
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", default=None, help="directory to keep the logs and runs in (default: a temporary one)")
    args = ap.parse_args(argv)
    counts = [int(w) for w in args.workers.split(",")]
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fleet-bench-"))
    logs = base / "logs"
    t0 = time.perf_counter()
    simulate_fleet(logs, robots=args.logs, days=1, minutes=args.minutes, seed=args.seed, wearing=0, force=True)
    print(f"simulated {args.logs} aibo logs of {args.minutes:g} min in {time.perf_counter() - t0:.1f} s ({logs})",
          file=sys.stderr)
    results = []
    for w in counts:
        t0 = time.perf_counter()
        res = calibrate_fleet(logs, base / f"out-{w}", workers=w, progress=False, force=True)
        wall = time.perf_counter() - t0
        ok = [r for r in res.rows if r["status"] == "ok"]
        cost = statistics.mean(r["seconds"] for r in ok)
        cpu = statistics.mean(r["cpu_seconds"] for r in ok)
        start, per_task = overhead(w)
        results.append((w, len(ok), wall, cost, cpu, start, per_task))
        print(f"  {w} worker(s): {wall:.1f} s", file=sys.stderr)
    print(f"\nfleet throughput: {args.logs} aibo logs of {args.minutes:g} min each, local cluster, "
          f"{os.cpu_count()} cores on this machine, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}\n")
    print("| workers | logs ok | wall s | logs/min (wall) | worker wall-s per log | worker CPU-s per log | "
          "logs/min at steady state | cluster start s | scheduler ms per task |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w, n, wall, cost, cpu, start, per_task in results:
        print(f"| {w} | {n} | {wall:.1f} | {60 * n / wall:.2f} | {cost:.2f} | {cpu:.2f} | {60 * w / cost:.2f} | "
              f"{start:.1f} | {1000 * per_task:.2f} |")
    cpu = statistics.mean(r[4] for r in results)            # a log's cost on a core of its own
    per_task = max(r[6] for r in results)
    print(f"\nlaw: throughput(N machines x c workers, a core each) ~ min(N c / {cpu:.2f} s, 1 / {per_task * 1000:.2f} ms)"
          f" logs/s = min({60 / cpu:.2f} N c, {60 / per_task:.0f}) logs/min, plus a fixed cluster start and the "
          f"drift/report tail per run; the scheduler bounds the fleet at about {cpu / per_task:.0f} workers")
    if len(results) > 1:
        a, b = results[0], results[-1]
        print(f"speed-up {a[0]} -> {b[0]} workers: {a[2] / b[2]:.2f}x wall, {(b[0] / b[3]) / (a[0] / a[3]):.2f}x steady "
              f"(cost per log {a[3]:.2f} -> {b[3]:.2f} s: workers share {os.cpu_count()} cores with everything else)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
