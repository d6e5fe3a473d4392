"""Calibrating a fleet: every log bundle under a directory, one Dask task each, then drift over time.

``calibrate_fleet(ROOT, OUT)`` finds every bundle under ROOT (a directory holding landmarks.csv,
commands.csv and observations.csv), calibrates each as ``casm-graph calibrate`` would (``load_log``,
``calibrate``, ``save`` into ``OUT/<the bundle's path under ROOT>/``) on a Dask cluster (a local one
of ``workers`` single-threaded processes, or the scheduler at ``scheduler``), and writes

* ``OUT/fleet.csv``: one row per bundle (path, robot, time, steps, minutes, the key model figures,
  fit quality, seconds, status ``ok``/``failed``/``skipped`` and the one-line error);
* ``OUT/fleet.json``: the rows and the drift analysis (:mod:`casm_graph.analysis.drift`), strict JSON;
* ``OUT/report.html``: the fleet side by side and each robot's figures over time
  (:mod:`casm_graph.report.fleet`).

Each bundle's run is written on its own, all or nothing (``Calibration.save``), so the runs finished
before a failure or an interruption stay; a second run skips every bundle whose run is complete
(model.json, trajectory.csv and report.html, made with the same method and effects) unless ``force``
and reads its row back from its model.json. A bundle that fails gets its reason in its row and does
not stop the others. fleet.csv, fleet.json and report.html are each replaced in one rename.

fleet.json (schema ``casm-graph/fleet/1``): ``rows`` (as fleet.csv, plus ``cpu_seconds`` and the
worker), ``counts``, ``options``, ``scheduler``, ``seconds``, and ``drift``: ``summary`` (one line per
drifted robot and family), ``drifted`` (robot -> families), ``families`` (every family comparison:
scale, its std, sigma, actions beyond 3 sigma, flagged), ``flags`` (every flagged figure) and
``series`` (per robot every figure over its sessions with its std); see :mod:`casm_graph.analysis.drift`.

A local cluster starts its workers by spawning processes, so a script that calls :func:`calibrate_fleet`
without ``scheduler`` must do so under ``if __name__ == "__main__":`` (the command line and notebooks
need nothing).
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import secrets
import shlex
import socket
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from distributed import Client, LocalCluster, as_completed
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from casm_graph.analysis import drift as driftmod
from casm_graph.io.log import LogError
from casm_graph.io.log import load as load_log
from casm_graph.io.output import checked_out, json_text
from casm_graph.models.effects import catalog
from casm_graph.models.model import ACTION_MODELS
from casm_graph.pipeline.calibrate import calibrate
from casm_graph.report import fleet as fleet_report
from casm_graph.sim.fleet import simulate_fleet

BUNDLE_FILES = ("landmarks.csv", "commands.csv", "observations.csv")
RUN_FILES = ("model.json", "trajectory.csv", "report.html")
MARKER = ".casm-fleet"                 # in OUT: this directory holds a fleet run (a second run may continue it)
SCHEMA = "casm-graph/fleet/1"
DEFAULT_WORKERS = 2
CONNECT_TIMEOUT = 20.0                 # s: how long to try reaching --scheduler, by default
BASE_COLUMNS = ("path", "robot", "time", "status", "error", "kind", "method", "steps", "minutes", "sightings",
                "actions", "mean_abs_vx", "mean_abs_vy", "mean_abs_w", "reading_sigma", "bearing_sigma",
                "motion_noise_x", "motion_noise_y", "motion_noise_theta")
TAIL_COLUMNS = ("log_likelihood", "converged", "iterations", "fit_seconds", "seconds", "cpu_seconds", "worker")


# --------------------------------------------------------------------------- finding the bundles

def find_bundles(root, exclude=None) -> list[Path]:
    """Every directory under ``root`` (``root`` included) holding landmarks.csv, commands.csv and
    observations.csv, sorted; hidden directories and ``exclude`` (e.g. the output) are not searched."""
    root = Path(root).expanduser().resolve()
    skip = Path(exclude).expanduser().resolve() if exclude is not None else None
    found = []
    for here, dirs, files in os.walk(root, followlinks=False):
        p = Path(here)
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and (skip is None or p / d != skip))
        if all(f in files for f in BUNDLE_FILES):
            found.append(p)
    return sorted(found)


def relative(bundle, root) -> str:
    """The bundle's path under ``root`` with '/' (the root's own name when the root is the bundle)."""
    bundle, root = Path(bundle).resolve(), Path(root).resolve()
    rel = bundle.relative_to(root).as_posix()
    return root.name if rel == "." else rel


def robot_and_time(bundle, root) -> tuple[str | None, str | None]:
    """(robot, time) of a bundle: from its meta.json ``{"robot", "time"}``, else from the path ROBOT/DATE/."""
    bundle = Path(bundle)
    robot = when = None
    meta = bundle / "meta.json"
    if meta.is_file():
        try:
            data = json.loads(meta.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            data = {}
        if isinstance(data, dict):
            robot = None if data.get("robot") is None else str(data["robot"])
            when = None if data.get("time") is None else str(data["time"])
    parts = Path(relative(bundle, root)).parts
    if robot is None and len(parts) >= 2:
        robot = parts[-2]
    if when is None and len(parts) >= 2:
        when = parts[-1]
    if robot is None and len(parts) == 1:
        robot = parts[0]
    return robot, when


# --------------------------------------------------------------------------- Dask

@contextmanager
def client_for(scheduler: str | None = None, workers: int | None = None,
               connect_timeout: float = CONNECT_TIMEOUT) -> Iterator:
    """A ``distributed.Client``: a LocalCluster of ``workers`` (default 2) single-threaded processes when
    ``scheduler`` is None, else the scheduler at that address (``tcp://host:port``) or scheduler file, tried
    for ``connect_timeout`` seconds; closed (with the local cluster) on the way out."""
    if scheduler is None:
        n = DEFAULT_WORKERS if workers is None else int(workers)
        if n < 1:
            raise LogError(f"--workers must be at least 1 (got {n})")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=logging.CRITICAL)
        try:
            with Client(cluster) as client:
                yield client
        finally:
            cluster.close()
        return
    try:
        if Path(scheduler).is_file():
            client = Client(scheduler_file=str(scheduler), timeout=f"{connect_timeout}s")
        else:
            client = Client(scheduler, timeout=f"{connect_timeout}s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise LogError(f"--scheduler {scheduler}: cannot connect ({_one_line(exc)})") from None
    try:
        yield client
    finally:
        client.close()


def _apply(fn, item):
    return fn(item)


def _one_blas_thread() -> None:
    threadpool_limits(1)                  # called as a function: the limit stays for the worker's life


class DaskPool:
    """A pool for emcee (``EnsembleSampler(..., pool=DaskPool(client))``) or anything that calls ``map``:
    each item is one task on the cluster; the results come back in order.

    ``fn`` must pickle (cloudpickle: a module-level function, a closure, emcee's wrapper of either). It is
    sent to every worker once (``scatter``) and reused while the same object is mapped again, as emcee
    does on every step, so a log-probability that holds a whole log travels once, not once per walker.
    Evaluations happen on the workers, so counters kept inside ``fn`` do not change in the caller: the
    pool counts ``calls``, ``items`` and the wall ``seconds`` spent in ``map`` instead. With
    ``one_blas_thread`` the workers present now get a single BLAS thread (small dense blocks: more
    threads only spin)."""

    def __init__(self, client, one_blas_thread: bool = True):
        self.client = client
        self._fn = None
        self._remote = None
        self.calls, self.items, self.seconds = 0, 0, 0.0
        if one_blas_thread:
            client.run(_one_blas_thread)

    def map(self, fn, iterable):
        items = list(iterable)
        if not items:
            return []
        t0 = time.perf_counter()
        if fn is not self._fn:
            self._remote = self.client.scatter(fn, broadcast=True, hash=False)
            self._fn = fn
        out = self.client.gather(self.client.map(_apply, [self._remote] * len(items), items, pure=False))
        self.calls += 1
        self.items += len(items)
        self.seconds += time.perf_counter() - t0
        return out


# --------------------------------------------------------------------------- one bundle (runs on a worker)

def _one_line(exc) -> str:
    s = " ".join(str(exc).split())
    return s if len(s) <= 300 else s[:300] + "..."


def _reason(exc: BaseException) -> str:
    return _one_line(exc) if isinstance(exc, LogError) else f"{type(exc).__name__}: {_one_line(exc)}"


def _f(x):
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def model_row(model: dict) -> dict:
    """The fleet-table figures of one model.json: sensor, noise, fit quality, and the action model in brief
    (a table: its size and mean absolute velocity per axis; a command map: its coefficients in the
    command's own units, ``v_coef_i`` = model.json's ``coefficients.v[i] / scale.v**i``)."""
    am, sm, fit = model.get("action_model", {}) or {}, model.get("sensor_model", {}) or {}, model.get("fit", {}) or {}
    row = {"kind": am.get("kind"), "method": fit.get("method")}
    part = ACTION_MODELS.get(am.get("kind"))
    for k, v in (part.brief(am) if part is not None else {}).items():
        row[k] = v if isinstance(v, int) else _f(v)
    row["reading_sigma"] = _f(sm.get("reading_sigma"))
    row["bearing_sigma"] = _f(sm.get("bearing_sigma"))
    for ax, v in zip(("x", "y", "theta"), model.get("motion_noise") or []):
        row[f"motion_noise_{ax}"] = _f(v)
    row["reading_basis"] = sm.get("reading_basis", "distance")      # the variable the coefficients are in
    for i, c in enumerate(sm.get("reading_poly") or []):
        row[f"reading_c{i}"] = _f(c)
    row["log_likelihood"] = _f(fit.get("log_likelihood"))
    row["converged"] = fit.get("converged")
    row["iterations"] = fit.get("iterations")
    row["fit_seconds"] = _f(fit.get("seconds"))
    return row


def log_row(log) -> dict:
    return {"steps": int(log.steps), "minutes": round(float(log.minutes), 4), "sightings": len(log.obs_t)}


def calibrate_bundle(bundle: str, run: str, method: str = "graph", effects: tuple = (), seed: int = 0,
                     force: bool = False, command: str | None = None) -> dict:
    """One fleet task: calibrate the bundle at ``bundle`` and save the run at ``run``; the row's figures.

    Never raises for a bad or failing bundle: the row has status ``failed`` and the one-line reason."""
    t0, c0 = time.perf_counter(), time.process_time()
    row: dict = {"status": "ok", "error": None}
    try:
        with threadpool_limits(1), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            log = load_log(bundle)
            row.update(log_row(log))
            cal = calibrate(log, method=method, effects=tuple(effects), seed=seed, command=command)
            cal.save(run, force=force)
        row.update(model_row(cal.model_json))
    except Exception as exc:  # noqa: BLE001  (the bundle's reason goes in its row; the others go on)
        row.update(status="failed", error=_reason(exc))
    row["seconds"] = round(time.perf_counter() - t0, 3)
    row["cpu_seconds"] = round(time.process_time() - c0, 3)
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return row


# --------------------------------------------------------------------------- the fleet

@dataclass
class FleetResult:
    """Rows (one per bundle, sorted by path), the drift analysis, where it was written, how long it took."""

    out: Path
    rows: list[dict]
    drift: driftmod.Drift
    seconds: float
    scheduler: str
    options: dict = field(default_factory=dict)

    @property
    def counts(self) -> dict[str, int]:
        c = {"ok": 0, "failed": 0, "skipped": 0}
        for r in self.rows:
            c[r["status"]] = c.get(r["status"], 0) + 1
        return c

    def to_json(self) -> dict:
        return {"schema": SCHEMA, "root": self.options.get("root"), "options": self.options, "counts": self.counts,
                "seconds": self.seconds, "scheduler": self.scheduler, "rows": self.rows, "drift": self.drift.to_json()}


def _complete(run: Path, method: str, effects: tuple) -> dict | None:
    """The model.json of a complete run made with ``method`` and ``effects``, else None."""
    if not all((run / f).is_file() for f in RUN_FILES):
        return None
    try:
        model = json.loads((run / "model.json").read_text())
        opts = model["fit"]["options"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        return None
    if opts.get("method") != method or list(opts.get("effects") or []) != list(effects):
        return None
    return model


def _check_out(out, force: bool, root: Path) -> Path:
    """OUT usable for a fleet: not an input's place, writable; new, empty, a fleet's earlier OUT, or ``force``."""
    path = checked_out(out, force=True, inputs=[root])
    if path.is_dir() and any(path.iterdir()) and not (path / MARKER).is_file() and not force:
        raise LogError(f"--out {out}: exists, is not empty and holds no fleet run; choose another directory or "
                       f"pass --force to write into it")
    return path


def _replace_file(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` in one rename (a temporary file next to it first)."""
    tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.partial"
    try:
        with open(tmp, "w", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def columns(rows: list[dict]) -> list[str]:
    """fleet.csv's header: the base columns, then the sensor and command-map coefficients present, then fit and time."""
    extra = []
    for r in rows:
        for k in r:
            if k not in BASE_COLUMNS and k not in TAIL_COLUMNS and k not in extra:
                extra.append(k)
    extra.sort(key=lambda k: (not k.startswith("reading_"), k))
    return [*BASE_COLUMNS, *extra, *TAIL_COLUMNS]


def csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    cols = columns(rows)
    w.writerow(cols)
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c)
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                cells.append("")
            elif isinstance(v, bool):
                cells.append("true" if v else "false")
            elif isinstance(v, float):
                cells.append(f"{v:.8g}")
            else:
                cells.append(str(v))
        w.writerow(cells)
    return buf.getvalue()


def calibrate_fleet(root, out, scheduler: str | None = None, method: str = "graph", effects=(), force: bool = False,
                    workers: int | None = None, progress: bool = True, seed: int = 0,
                    command: str | None = None, connect_timeout: float = CONNECT_TIMEOUT) -> FleetResult:
    """Calibrate every bundle under ``root`` into ``out`` on Dask; rows, drift, fleet.csv/json, report.html.

    Bad input (no such directory, no bundles, an unusable ``out``, an unknown effect, an unreachable
    scheduler) raises LogError before any bundle is calibrated."""
    t0 = time.perf_counter()
    root_p = Path(root).expanduser().resolve()
    if not root_p.is_dir():
        raise LogError(f"{root}: no such directory")
    effects = tuple(effects)
    known = {c["name"] for c in catalog()}
    for e in effects:
        if e not in known:
            raise LogError(f"unknown effect {e!r} (known: {', '.join(sorted(known))})")
    out_p = _check_out(out, force, root_p)
    bundles = find_bundles(root_p, exclude=out_p)
    if not bundles:
        raise LogError(f"{root}: no log bundles under it (directories with {', '.join(BUNDLE_FILES)})")
    rels = [relative(b, root_p) for b in bundles]
    if len(set(rels)) != len(rels):
        raise LogError(f"{root}: two bundles would share one run directory in --out")

    out_p.mkdir(parents=True, exist_ok=True)
    (out_p / MARKER).write_text(json_text({"schema": SCHEMA, "root": str(root_p)}) + "\n")
    rows, todo = [], []
    for b, rel in zip(bundles, rels):
        robot, when = robot_and_time(b, root_p)
        head = {"path": rel, "robot": robot, "time": when}
        run = out_p / rel
        done = None if force else _complete(run, method, effects)
        if done is not None:
            row = {**head, "status": "skipped", "error": None}
            try:
                row.update(log_row(load_log(b)))
            except LogError:
                pass
            row.update(model_row(done))
            row["seconds"] = 0.0
            rows.append(row)
        else:                     # new, or an incomplete / differently made run of ours: (re)made and replaced
            todo.append((head, str(b), str(run), force or run.exists()))

    label = scheduler if scheduler is not None else "local"
    if todo:
        with client_for(scheduler, workers, connect_timeout) as client:
            label = scheduler if scheduler is not None else f"local cluster, {len(client.scheduler_info()['workers'])} workers"
            futures = {}
            for head, b, run, replace in todo:
                fut = client.submit(calibrate_bundle, b, run, method, effects, seed, replace, command, pure=False,
                                    key=f"casm-fleet-{head['path']}-{secrets.token_hex(4)}")
                futures[fut] = head
            with tqdm(total=len(todo), desc="fleet", unit="log", file=sys.stderr, disable=not progress,
                      dynamic_ncols=True) as bar:
                for fut in as_completed(futures):
                    head = futures[fut]
                    try:
                        row = {**head, **fut.result()}
                    except Exception as exc:  # noqa: BLE001  (the task died: a worker lost, a pickling error)
                        row = {**head, "status": "failed", "error": _reason(exc)}
                    rows.append(row)
                    bar.set_postfix_str(f"{head['path']}: {row['status']}", refresh=False)
                    bar.update(1)
    rows.sort(key=lambda r: r["path"])

    sessions = []
    for r in rows:
        if r["status"] in ("ok", "skipped") and r.get("robot") is not None and r.get("time") is not None:
            try:
                model = json.loads((out_p / r["path"] / "model.json").read_text())
            except (OSError, json.JSONDecodeError, UnicodeDecodeError):
                continue
            sessions.append(driftmod.Session(robot=r["robot"], time=r["time"], path=r["path"], model=model))
    drift = driftmod.analyse(sessions)
    options = {"root": str(root_p), "method": method, "effects": list(effects), "seed": seed, "force": force,
               "scheduler": scheduler, "workers": workers, "connect_timeout": connect_timeout, "command": command}
    result = FleetResult(out=out_p, rows=rows, drift=drift, seconds=round(time.perf_counter() - t0, 3),
                         scheduler=label, options=options)
    _replace_file(out_p / "fleet.csv", csv_text(rows))
    _replace_file(out_p / "fleet.json", json_text(result.to_json()))
    _replace_file(out_p / "report.html", fleet_report.render(result))
    return result


# --------------------------------------------------------------------------- command line

def _fleet(args) -> int:
    argv = getattr(args, "argv", None)
    result = calibrate_fleet(args.dir, args.out, scheduler=args.scheduler, method=args.method,
                             effects=tuple(args.effect), force=args.force, workers=args.workers,
                             progress=not args.quiet, connect_timeout=args.connect_timeout,
                             command=shlex.join(["casm-graph", *argv]) if argv is not None else None)
    c = result.counts
    print(f"fleet: {len(result.rows)} bundles under {args.dir}: {c['ok']} calibrated, {c['skipped']} skipped "
          f"(complete), {c['failed']} failed, in {result.seconds:.0f} s on {result.scheduler}")
    for r in result.rows:
        if r["status"] == "failed":
            print(f"  failed {r['path']}: {r['error']}")
    lines = result.drift.summary
    print(f"  drift: {len(lines)} finding(s)" + (":" if lines else " (no robot changed beyond its uncertainty)"))
    for line in lines:
        print("    " + line)
    print(f"  wrote {args.out}/fleet.csv, fleet.json, report.html and a run per bundle")
    if c["failed"] and not c["ok"] and not c["skipped"]:
        print("casm-graph: error: every bundle failed", file=sys.stderr)
        return 1
    return 0


def _simulate_fleet(args) -> int:
    truth = simulate_fleet(args.out, robots=args.robots, days=args.days, minutes=args.minutes, seed=args.seed,
                           wearing=args.wearing, wear_per_day=args.wear_per_day, force=args.force)
    print(f"wrote {args.out}: {args.robots} robots x {args.days} days of {args.minutes:g}-minute aibo logs; "
          f"wearing ({100 * args.wear_per_day:g} % of every velocity per day): {', '.join(truth['wearing']) or 'none'}"
          f" (fleet_truth.json)")
    return 0


def add_commands(sub) -> None:
    """Add ``fleet`` and ``simulate-fleet`` to the ``casm-graph`` subcommands ``sub``."""
    f = sub.add_parser("fleet", help="calibrate every log bundle under DIR on Dask and show which robot drifted")
    f.add_argument("dir", help="directory searched for log bundles (ROBOT/DATE/ or a meta.json gives robot and time)")
    f.add_argument("--out", required=True)
    f.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:port) or scheduler file; default a local cluster")
    f.add_argument("--method", default="graph")
    f.add_argument("--effect", action="append", default=[], metavar="NAME")
    f.add_argument("--workers", type=int, default=None,
                   help=f"processes of the local cluster (default {DEFAULT_WORKERS}; ignored with --scheduler)")
    f.add_argument("--connect-timeout", type=float, default=CONNECT_TIMEOUT, metavar="SECONDS",
                   help=f"how long to try reaching --scheduler (default {CONNECT_TIMEOUT:g})")
    f.add_argument("--force", action="store_true", help="recalibrate bundles whose run is complete; write into a "
                                                        "non-empty --out")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.set_defaults(func=_fleet)
    s = sub.add_parser("simulate-fleet", help="write simulated logs of many robots over several days, some wearing")
    s.add_argument("out")
    s.add_argument("--robots", type=int, default=20)
    s.add_argument("--days", type=int, default=5)
    s.add_argument("--minutes", type=float, default=3.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--wearing", type=int, default=2, help="robots whose velocities shrink day by day")
    s.add_argument("--wear-per-day", type=float, default=0.04, help="share of every velocity lost per day")
    s.add_argument("--force", action="store_true", help="replace OUT if it exists and is not empty")
    s.set_defaults(func=_simulate_fleet)
