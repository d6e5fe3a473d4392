"""The ``casm-graph`` command line (INTERFACE section 2).

Exit status 0 on success, 2 on bad input (one clear message, nothing written), 1 on any other failure.
"""
from __future__ import annotations

import argparse
import contextlib
import ctypes
import multiprocessing
import os
import shlex
import signal
import sys
import threading
import time
import warnings

from tqdm import tqdm

from casm_graph.fit.calibration import cross_term_words
from casm_graph.fit.methods import METHODS, Progress
from casm_graph.io import mrclam, plaza
from casm_graph.io.log import LogError
from casm_graph.models.command_model import STEP_HEADINGS
from casm_graph.io.output import atomic_dir, checked_out, discard_partial
from casm_graph.models.effects import catalog, proposal
from casm_graph.models.effects.regional_motion_noise import determined
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.pipeline import compare, fleet
from casm_graph.pipeline import diagnose as diagnose_run
from casm_graph.pipeline import uncertainty as uncertainty_run
from casm_graph.sim import protocols as simulators


class Bar(Progress):
    """A tqdm bar per stage on stderr, showing the current cost."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bar = None
        self.t0 = time.perf_counter()

    def stage(self, name, total=None, unit="rounds"):
        self.close()
        if self.enabled:
            self.bar = tqdm(total=total, desc=f"{name:>12}", unit="it", leave=True, file=sys.stderr,
                            bar_format="{desc}: {percentage:3.0f}%|{bar:24}| {n_fmt}/{total_fmt} " + unit
                            + " [{elapsed}]{postfix}"
                            if total else "{desc}: [{elapsed}]")

    def step(self, n=1, **info):
        if self.bar is not None:
            if "cost" in info:
                self.bar.set_postfix_str(f"cost {info['cost']:.1f}", refresh=False)
            if n:
                self.bar.update(n)
            else:
                self.bar.refresh()

    def close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _simulate(args) -> int:
    checked_out(args.out, args.force)
    effects = {}
    for item in args.effect:
        name, sep, value = item.partition("=")
        try:
            effects[name] = float(value) if sep else 1.0
        except ValueError:
            raise LogError(f"--effect {item!r}: value must be a number (NAME=VALUE)") from None
    options = {"reading_sigma": args.reading_sigma}
    if args.protocol == "aibo":
        options["bearing_sigma"] = args.bearing_sigma
    if args.protocol == "floor":
        options = {}
    options.update(simulators.parse_options(args.protocol, args.option, taken=tuple(options)))
    if args.sensor is not None:
        options["sensor"] = args.sensor
    log, truth = simulators.simulate(args.protocol, minutes=args.minutes, seed=args.seed, effects=effects, **options)
    with atomic_dir(args.out, force=args.force) as tmp:
        simulators.write_log(log, tmp, truth)
    print(f"wrote {args.out}: {args.protocol}, {log.steps} steps, {len(log.obs_t)} observations, {log.minutes:.1f} min")
    return 0


def _requested_effects(args) -> tuple:
    """``--effect`` names, ``proposal`` replaced by the effect the ``--proposal`` diagnosis proposed."""
    if "proposal" not in args.effect:
        if args.proposal:
            raise LogError("--proposal DIAG is read only with --effect proposal")
        return tuple(args.effect)
    if not args.proposal:
        raise LogError("--effect proposal needs --proposal DIAG: the diagnosis (directory or diagnosis.json) "
                       "that proposed it")
    made = proposal.from_diagnosis(args.proposal)
    return tuple(made if e == "proposal" else e for e in args.effect)


def _calibrate(args) -> int:
    bar = Bar(enabled=not args.quiet)
    if args.method in calibrate_run.SCASM_METHODS:
        try:
            _, model = calibrate_run.run(args.log, args.out, method=args.method, progress=bar, force=args.force,
                                         command=command_line(args))
        finally:
            bar.close()
        print(f"calibrated {args.log} with {args.method} in {model['fit']['seconds']:.1f} s")
        for k, v in model["fit"].get("evaluation", {}).items():
            print(f"  {k} {v:.4g}")
        print(f"  wrote {args.out}/model.json, trajectory.csv, report.html")
        return 0
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            log, fit = calibrate_run.run(args.log, args.out, method=args.method, sensor_degree=args.sensor_degree,
                                         max_sensor_degree=args.max_sensor_degree,
                                         sensor_basis=args.sensor_basis,
                                         cross_terms={"on": True, "off": False}.get(args.cross_terms, "auto"),
                                         step_heading=args.step_heading,
                                         effects=_requested_effects(args), seed=args.seed, progress=bar, regions=args.regions,
                                         force=args.force, command=command_line(args))
    finally:
        bar.close()
    for msg in dict.fromkeys(str(w.message) for w in caught):
        print(f"casm-graph: warning: {msg}", file=sys.stderr)
    m = fit.model
    if not m.fit.get("converged", True):
        print("casm-graph: warning: the optimiser stopped before converging (see the cost per iteration in "
              f"{args.out}/report.html)", file=sys.stderr)
    print(f"calibrated {args.log} with {args.method} in {m.fit['seconds']:.1f} s "
          f"({m.fit['iterations']} iterations, converged={m.fit['converged']})")
    print(f"  reading sigma {m.noise_text('reading', '.3f')}, bearing sigma {m.noise_text('bearing', '.3f')}"
          + (" rad" if m.has("bearing") else ""))
    slopes = m.fit.get("start_slopes", [])
    if len(slopes) > 1:
        print(f"  range start slope {max(slopes, key=lambda t: t[1])[0]:.3f}, the likeliest after the held coarse "
              "rounds of " + ", ".join(f"{s:.3f} (log-likelihood {ll:,.0f})" for s, ll in slopes))
    if m.fit.get("cross_term"):
        print("  " + cross_term_words(m.fit["cross_term"]))
    if "regional_motion_noise" in m.effects:
        e = m.effects["regional_motion_noise"]
        for g, (kr, kt, kd, ok) in enumerate(zip(e["k_r"], e["k_t"], e["k_d"], determined(e))):
            n = e.get("segments", [0] * len(e["k_r"]))[g]
            print(f"  region {g}: k_r {kr:.2g} m, k_t {kt:.2g} rad, k_d {kd:.2g} rad^2/m, {n} segments"
                  + ("" if ok else " (undetermined: the start's values)"))
    print(f"  wrote {args.out}/model.json, trajectory.csv, report.html")
    return 0


def _diagnose(args) -> int:
    bar = Bar(enabled=not args.quiet)
    try:
        with (fleet.client_for(args.scheduler) if args.scheduler else contextlib.nullcontext()) as client:
            diag = diagnose_run.run(args.log, args.model, args.out, workers=args.workers, progress=bar,
                                    candidates=args.candidate, force=args.force, client=client, before=args.before)
    finally:
        bar.close()
    print(diag.summary())
    print(f"  wrote {args.out}/diagnosis.json, report.html")
    return 0


def _import_mrclam(args) -> int:
    checked_out(args.out, args.force, inputs=[args.dir])
    with atomic_dir(args.out, force=args.force, inputs=[args.dir]) as tmp:
        log, info = mrclam.import_robot(args.dir, args.robot, tmp)
    print(f"wrote {args.out}: robot {args.robot}, {log.steps} command steps ({info['command_rows_dropped']} "
          f"repeated times dropped), {len(log.obs_t)} landmark observations "
          f"({info['robot_sightings_dropped']} sightings of robots dropped), {log.minutes:.1f} min, truth.csv from Vicon")
    return 0


def _import_plaza(args) -> int:
    log, info = plaza.import_plaza(args.file, args.out, force=args.force, minutes=args.minutes)
    dropped = "; ".join(plaza.drops(info)) or "none dropped"
    cut = f", {info['ranges_after_minutes_cut']} later ranges cut" if args.minutes is not None else ""
    print(f"wrote {args.out}: Plaza 1, {log.steps} command steps, {len(log.obs_t)} range observations "
          f"({dropped}{cut}), {log.minutes:.1f} min, truth.csv from GT")
    return 0


def _effects(args) -> int:
    for c in catalog():
        orders = (f"  (orders {', '.join(map(str, c['orders']))}; default {c['order']}: NAME:ORDER)"
                  if c.get("orders") else "")
        print(f"{c['name']:<22} {c['channel']:<7} {', '.join(c['parameters'])}{orders}")
        print(f"{'':<30}{c['physics']}")
    return 0


def _uncertainty(args) -> int:
    bar = Bar(enabled=not args.quiet)
    try:
        with warnings.catch_warnings(record=True), \
                (fleet.client_for(args.scheduler) if args.scheduler else contextlib.nullcontext()) as client:
            warnings.simplefilter("always", RuntimeWarning)
            unc = uncertainty_run.run(args.log, args.model, args.out, priors=tuple(args.prior), walkers=args.walkers,
                                      max_steps=args.max_steps, seed=args.seed, progress=bar, force=args.force,
                                      pool=fleet.DaskPool(client) if client is not None else None)
    finally:
        bar.close()
    ch = unc.chain
    print(f"posterior of {len(ch.names)} noise levels in {unc.seconds:.0f} s: {ch.walkers} walkers x {ch.steps} steps "
          f"(burn-in {ch.burn_in}), {1000 * ch.seconds_per_evaluation:.1f} ms per likelihood evaluation")
    for n, s in unc.intervals.items():
        print(f"  {n:<24} {s['median']:.4g}  90% [{s['ci90'][0]:.4g}, {s['ci90'][1]:.4g}]")
    if unc.ml.set_aside():
        print(f"  {unc.ml.set_aside()} sighting(s) set aside as gross outliers")
    for note in ch.notes:
        print(f"casm-graph: warning: {note}", file=sys.stderr)
    print(f"  wrote {args.out}/posterior.json, model.json, corner.png, trace.png, report.html")
    return 0


def _compare(args) -> int:
    res = compare.run(args.model, args.measured, args.out, force=args.force)
    for line in res["summary"]:
        print(line)
    print(f"  wrote {args.out}/comparison.json, report.html")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="casm-graph", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("simulate", help="write a simulated Aibo log bundle with its truth")
    s.add_argument("out")
    s.add_argument("--minutes", type=float, default=15.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--reading-sigma", type=float, default=1.0, help="reading noise (px)")
    s.add_argument("--bearing-sigma", type=float, default=0.5, help="bearing noise (rad)")
    s.add_argument("--effect", action="append", default=[], metavar="NAME=VALUE")
    s.add_argument("--protocol", default="aibo", choices=["aibo", "scasm-1d", "floor"],
                   help="aibo: the EKFS-EM field (default); scasm-1d: SCASM's walk to and from one beacon; "
                        "floor: a wheeled robot on a floor whose motion noise differs by region (MCL paper)")
    s.add_argument("--sensor", default=None, choices=["range", "bearing", "both"],
                   help="which cells the observations fill: range (readings only; on the floor seen all around), "
                        "bearing (bearings only) or both (default); aibo and floor only")
    s.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                   help="set a field of the protocol's simulator config (repeatable), e.g. floor: n_landmarks=4, "
                        "range_scale=1.05, range_offset=0.3, nlos_fraction=0.1, nlos_scale=1.5, size=10,6")
    s.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    s.set_defaults(func=_simulate)
    c = sub.add_parser("calibrate", help="learn the action and sensor models of a log")
    c.add_argument("log")
    c.add_argument("--out", required=True)
    c.add_argument("--method", default="graph", choices=sorted(METHODS) + ["scasm", "scasm-graph"])
    c.add_argument("--effect", action="append", default=[], metavar="NAME",
                   help="add a catalog effect (repeatable; NAME:ORDER for a family's member, e.g. surface_friction:1); "
                        "'proposal' adds the one a diagnosis proposed (--proposal)")
    c.add_argument("--proposal", default=None, metavar="DIAG",
                   help="the diagnosis (directory or diagnosis.json) whose proposed effect --effect proposal adds")
    c.add_argument("--sensor-degree", type=int, default=3, help="degree of the sensor polynomial (the paper's 3)")
    c.add_argument("--max-sensor-degree", type=int, default=6,
                   help="the graph method raises the degree up to this when the readings demand a bendier curve "
                        "(set it to --sensor-degree to keep that degree)")
    c.add_argument("--sensor-basis", default="auto", choices=("auto", "distance", "inverse_distance"),
                   help="the sensor curve's variable: a polynomial in the distance (the paper's) or in 1/distance, "
                        "for a reading that is an apparent size (pixels), which falls as 1/d; auto (default): the "
                        "distance, and 1/d competing when the fit in d misses near the landmarks (graph method)")
    c.add_argument("--cross-terms", default="auto", choices=("auto", "on", "off"),
                   help="continuous v,w commands: the turn map also linear in v (turn rate += c v), the turn a "
                        "differential drive's unequal wheels add to every forward command; auto (default): the "
                        "graph method keeps it when BIC supports it; off: each map reads its own command only")
    c.add_argument("--step-heading", default="auto", choices=("auto", *STEP_HEADINGS),
                   help="the heading each step moves the robot along: its start (the paper's step) or its middle "
                        "(the chord of the arc a command held over the step drives); auto (default): an action "
                        "table's steps the start, continuous commands' the middle")
    c.add_argument("--regions", default=None, metavar="NX,NY[,X0,Y0,X1,Y1]",
                   help="grid of the regional_motion_noise effect (default 3,2 around the landmarks)")
    c.add_argument("--seed", type=int, default=0, help="seed of the randomised trace estimates")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    c.set_defaults(func=_calibrate)
    d = sub.add_parser("diagnose", help="where the model fails and which effect is missing")
    d.add_argument("log")
    d.add_argument("--model", required=True, help="RUN/model.json (RUN/trajectory.csv is used as the start when present)")
    d.add_argument("--out", required=True)
    d.add_argument("--workers", type=int, default=2, help="processes fitting candidates in parallel")
    d.add_argument("--candidate", action="append", default=None, metavar="NAME",
                   help="try only this effect (repeatable; default: every applicable catalog effect)")
    d.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="fit the candidates and folds on this Dask scheduler (tcp://host:port or a scheduler file)")
    d.add_argument("--before", default=None, metavar="DIAG",
                   help="an earlier diagnosis of this log (its directory or diagnosis.json): show what changed")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    d.set_defaults(func=_diagnose)
    i = sub.add_parser("import-mrclam", help="convert one robot of the UTIAS MRCLAM dataset into a log bundle")
    i.add_argument("dir", help="directory with the dataset's .dat files (one run)")
    i.add_argument("--robot", type=int, required=True, help="robot number 1..5")
    i.add_argument("--out", required=True)
    i.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    i.set_defaults(func=_import_mrclam)
    pz = sub.add_parser("import-plaza", help="convert the CMU Plaza 1 range-only data set into a log bundle")
    pz.add_argument("file", metavar="FILE.mat", help="the data set's Plaza1.mat")
    pz.add_argument("--out", required=True, metavar="LOG")
    pz.add_argument("--minutes", type=float, default=None, metavar="M", help="keep only the first M minutes")
    pz.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    pz.set_defaults(func=_import_plaza)
    e = sub.add_parser("effects", help="list the effect catalog")
    e.set_defaults(func=_effects)
    u = sub.add_parser("uncertainty", help="posterior of the noise levels (emcee) and Laplace std of the rest")
    u.add_argument("log")
    u.add_argument("--model", required=True, help="RUN/model.json (RUN/trajectory.csv is used as the start when present)")
    u.add_argument("--out", required=True)
    u.add_argument("--prior", action="append", default=[], metavar="NAME=KIND:A:B",
                   help="override a prior: KIND loguniform, uniform (bounds A, B), lognormal (median, sd of log) "
                        "or normal (mean, sd); NAME as in posterior.json")
    u.add_argument("--walkers", type=int, default=None, help="emcee walkers (default 2 per sampled quantity + 2, at least 12)")
    u.add_argument("--max-steps", type=int, default=5000,
                   help="stop here even if the chain is not yet 50 autocorrelation times long (warns)")
    u.add_argument("--seed", type=int, default=0)
    u.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="evaluate emcee's walkers on this Dask scheduler (tcp://host:port or a scheduler file)")
    u.add_argument("--quiet", action="store_true", help="no progress bar")
    u.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    u.set_defaults(func=_uncertainty)
    k = sub.add_parser("compare", help="the learned model against independently measured tables")
    k.add_argument("model")
    k.add_argument("--measured", required=True, help="directory with sensor.csv and/or actions.csv")
    k.add_argument("--out", default="compare")
    k.add_argument("--force", action="store_true", help="replace --out if it exists and is not empty")
    k.set_defaults(func=_compare)
    fleet.add_commands(sub)
    return p


def _stop(signum, frame):
    """SIGTERM or Ctrl-C: stop the workers, remove every half-written output, leave at once.

    Leaving from the handler itself, not by raising: a signal can land while the main thread runs a
    C callback (numba's compiler, GTSAM), where a raised exception would be swallowed."""
    for child in multiprocessing.active_children():
        child.terminate()
    discard_partial()
    word = "terminated" if signum == signal.SIGTERM else "interrupted"
    print(f"casm-graph: {word}; nothing written", file=sys.stderr, flush=True)
    os._exit(1)


def command_line(args) -> str:
    """The command as typed (for the record in model.json)."""
    return shlex.join(["casm-graph", *args.argv])


def steady_heap() -> bool:
    """Ask glibc to keep freed large blocks for reuse instead of returning them to the kernel: a fit allocates and
    frees the same large temporaries every iteration, and refaulting their pages cost a quarter of a candidate
    fit's time (BENCHMARKS.md). The program's own setting, made by the ``casm-graph`` command only; False where the C
    library is not glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(-3, 1 << 30)) and bool(libc.mallopt(-1, 1 << 30))   # M_MMAP_ and M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False


def command() -> int:
    """The ``casm-graph`` executable: the process's heap setting, then :func:`main`."""
    steady_heap()
    return main()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    args = parser().parse_args(argv)
    args.argv = argv
    own = threading.current_thread() is threading.main_thread()      # only the main thread may set handlers
    previous = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGINT)} if own else {}
    try:
        return args.func(args)
    except LogError as exc:
        print(f"casm-graph: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:   # the reader of our output left (``| head``): nothing to say, and no one to say it to
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except Exception as exc:  # any other failure: one line, status 1
        first = (str(exc).strip().splitlines() or [""])[0]       # one line, even for GTSAM's many-line messages
        print(f"casm-graph: failed: {type(exc).__name__}: {first}", file=sys.stderr)
        return 1
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(command())
