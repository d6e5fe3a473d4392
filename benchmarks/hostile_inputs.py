"""Hostile inputs through the command line (issue 23): bad data never wrecks a model, accepted logs never crash,
output is all or nothing.

    OPENBLAS_NUM_THREADS=1 python benchmarks/hostile_inputs.py [-k TEXT] [--no-probes] [--work DIR] [--json FILE]

Runs ``casm-graph`` (as ``python -m casm_graph.cli`` under this interpreter, so ``PYTHONPATH`` picks the version
measured) on simulated 3-minute logs (an Aibo action-table log and a ``--protocol floor`` one, seed 0) made
hostile. The issue's cases: A, logs once accepted that then crashed (3 commands, an action of one step, times
scaled by 1e300 or 1e-300, a coordinate or a reading of 1e300); B, garbage that exited 0 (one sighting, all
landmarks at one place, ids 2^53 and 2^53+1, '1_350' and non-ASCII digits); C, an ``--out`` that is empty, a
file, read-only, immutable, non-empty, the log directory, its parent, a symlink to it or the run holding the input
model; D, model files that are a list, binary, deeply nested, with a zero or negative sigma or a NaN; E, one and
five readings x 10,000. Unless ``--no-probes``, probes beside them (P): values just inside the loader's bounds,
the fewest sightings, near-coincident landmarks, more outliers, outliers under ``--method graph-em`` and
``ekfs-em``, diagnose and uncertainty on an outlier log, more bad model files.

Rule checked, per run: exit 0 with a sane model (strict JSON without NaN or Infinity, every expected file
written, sigmas and coefficients within bounds and, where the case says so, close to the clean log's) or exit 2
with exactly one stderr line; never a traceback or numpy / LAPACK text, exit 1, a timeout (300 s), an output path
changed by a failed run or a changed input. Each run has --quiet, an 8 GiB address-space cap and the machine to
itself (one at a time). The case run as user 'nobody' (setpriv) and the one with an immutable directory (chattr)
are SKIP where that is not possible. Prints a markdown table (case | exit | first stderr line | verdict) and the
count of FAILs, and exits 1 if any. ``-k TEXT`` (repeatable) runs only the cases whose name contains TEXT; the
clean logs and their calibrations are made when a selected case first needs them. ``--work`` (new or empty;
default a temporary directory) keeps the logs and outputs.
"""
from __future__ import annotations

import argparse
import copy
import csv
import hashlib
import json
import math
import os
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TIMEOUT = 300                 # seconds per run
MEM_CAP = 8 * 2 ** 30         # address space per run: one probe once grew to 22 GB RSS and was OOM-killed
NOBODY = "65534"
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
SIMULATE = {"aibo": [], "floor": ["--protocol", "floor"]}
EXPECTED = {"calibrate": ["model.json", "trajectory.csv", "report.html"],
            "diagnose": ["diagnosis.json", "report.html"],
            "uncertainty": ["posterior.json", "model.json", "corner.png", "trace.png", "report.html"],
            "compare": ["comparison.json", "report.html"]}
BIG = {"0": "9007199254740992", "1": "9007199254740993"}        # 2^53 and 2^53 + 1: equal as doubles


class Skip(Exception):
    """A case that cannot run on this machine (raised by its setup, with the reason)."""


def _cap_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEM_CAP, MEM_CAP))


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "casm_graph.cli", *args]


def strict_json(path: Path):
    def bad(c):
        raise ValueError(f"non-finite constant {c}")
    return json.loads(path.read_text(), parse_constant=bad)


def snapshot(p: Path):
    """State of a path: dangling link, absent, a file's hash, or a directory's {relative path: hash}."""
    if p.is_symlink() and not p.exists():
        return ("dangling",)
    if not p.exists():
        return ("absent",)
    if p.is_file():
        return ("file", hashlib.sha1(p.read_bytes()).hexdigest())
    files = {}
    for f in sorted(p.rglob("*")):
        if f.is_file():
            files[str(f.relative_to(p))] = hashlib.sha1(f.read_bytes()).hexdigest()
        elif f.is_dir():
            files[str(f.relative_to(p)) + "/"] = "dir"
    return ("dir", tuple(sorted(files.items())))


def unfreeze(p: Path) -> None:
    """Drop an immutable flag left on ``p`` (if any, and if chattr exists)."""
    if p.exists():
        try:
            subprocess.run(["chattr", "-i", str(p)], stderr=subprocess.DEVNULL, check=False)
        except FileNotFoundError:
            pass


def read_csv(path: Path):
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def write_csv(path: Path, header, rows) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)


def walk(o, path=""):
    """(path, number) for every number in a JSON value."""
    if isinstance(o, dict):
        for k, v in o.items():
            yield from walk(v, f"{path}.{k}")
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from walk(v, f"{path}[{i}]")
    elif isinstance(o, (int, float)) and not isinstance(o, bool):
        yield path, o


def model_problems(m: dict, base: dict | None) -> list[str]:
    """Sanity of a model.json: absurd sigmas (or far from the clean model's), collapsed distances, huge or vanishing
    numbers."""
    probs = []
    sm = m.get("sensor_model") or {}
    for key in ("reading_sigma", "bearing_sigma"):
        s = sm.get(key)
        if s is None:
            continue
        if not s > 0:
            probs.append(f"{key}={s}")
            continue
        if base and (base.get("sensor_model") or {}).get(key):
            r = s / base["sensor_model"][key]
            if r < 1e-2 or r > 1e2:
                probs.append(f"{key}={s:.3g} ({r:.2g}x clean)")
        elif s < 1e-6 or s > 1e4:
            probs.append(f"{key}={s:.3g}")
    for i, s in enumerate(m.get("motion_noise") or []):
        if s is not None and (s < 1e-7 or s > 1e3):
            probs.append(f"motion_noise[{i}]={s:.3g}")
        elif s is not None and base and base.get("motion_noise"):
            r = s / base["motion_noise"][i]
            if r < 1e-2 or r > 1e2:
                probs.append(f"motion_noise[{i}]={s:.3g} ({r:.2g}x clean)")
    dr, dr0 = sm.get("distance_range"), (base or {}).get("sensor_model", {}).get("distance_range")
    if dr and dr0 and dr[1] < 0.1 * dr0[1]:
        poly = [float(f"{c:.3g}") for c in sm.get("reading_poly") or []]
        probs.append(f"distances collapsed: distance_range {dr[0]:.2g}-{dr[1]:.2g} m "
                     f"(clean {dr0[0]:.2g}-{dr0[1]:.2g}), reading_poly {poly}")
    for path, v in walk({k: v for k, v in m.items() if k != "fit"}):
        lim = 1e12 if "reading_poly_cov" in path else 1e6
        if abs(v) > lim or (v != 0 and abs(v) < 1e-100):
            probs.append(f"{path}={v:.3g}")
    return probs


# ------------------------------------------------------------------------------------------------- log mutations
def set_cell(d: Path, file: str, row: int, column: str, value: str) -> None:
    h, rows = read_csv(d / file)
    rows[row][h.index(column)] = value
    write_csv(d / file, h, rows)


def cell(file, row, column, value):
    return lambda d: set_cell(d, file, row, column, value)


def scale_times(factor: float):
    def m(d: Path):
        for f in ("commands.csv", "observations.csv", "truth.csv"):
            h, rows = read_csv(d / f)
            i = h.index("t")
            for r in rows:
                r[i] = repr(float(r[i]) * factor)
            write_csv(d / f, h, rows)
    return m


def keep_commands(pick):
    """Only the command rows ``pick(number of rows)``, and the sightings within their span (the last row lasting the
    median step)."""
    def m(d: Path):
        h, rows = read_csv(d / "commands.csv")
        med = float(rows[1][0]) - float(rows[0][0])
        keep = [rows[i] for i in pick(len(rows))]
        write_csv(d / "commands.csv", h, keep)
        ts = [float(r[0]) for r in keep]
        step = sorted(b - a for a, b in zip(ts, ts[1:]))[len(ts) // 2 - 1] if len(ts) > 1 else med
        ho, obs = read_csv(d / "observations.csv")
        write_csv(d / "observations.csv", ho, [r for r in obs if ts[0] <= float(r[0]) <= ts[-1] + step])
    return m


def first_sightings(n: int):
    def m(d: Path):
        h, rows = read_csv(d / "observations.csv")
        write_csv(d / "observations.csv", h, rows[:n])
    return m


def landmarks_one_place(d: Path) -> None:
    h, rows = read_csv(d / "landmarks.csv")
    x, y = rows[0][1], rows[0][2]
    for r in rows:
        r[1], r[2] = x, y
    write_csv(d / "landmarks.csv", h, rows)


def big_ids(d: Path) -> None:
    for file, column in (("landmarks.csv", "landmark"), ("observations.csv", "landmark")):
        h, rows = read_csv(d / file)
        i = h.index(column)
        for r in rows:
            r[i] = BIG.get(r[i], r[i])
        write_csv(d / file, h, rows)


def scale_reading(n: int, factor: float, column: str = "reading"):
    """``n`` non-empty values of ``column``, spread over the log, multiplied by ``factor``."""
    def m(d: Path):
        h, rows = read_csv(d / "observations.csv")
        i = h.index(column)
        idx = [k for k, r in enumerate(rows) if r[i] != ""]
        for j in range(1, n + 1):
            k = idx[int(j * len(idx) / (n + 1))]
            rows[k][i] = repr(float(rows[k][i]) * factor)
        write_csv(d / "observations.csv", h, rows)
    return m


def spread_obs(n: int):
    def m(d: Path):
        h, rows = read_csv(d / "observations.csv")
        i, j = h.index("reading"), h.index("bearing")
        ok = [r for r in rows if r[i] != "" and r[j] != ""]
        write_csv(d / "observations.csv", h, [ok[int(k * (len(ok) - 1) / (n - 1))] for k in range(n)])
    return m


def landmarks_near(eps: float):
    def m(d: Path):
        h, rows = read_csv(d / "landmarks.csv")
        x, y = float(rows[0][1]), float(rows[0][2])
        for k, r in enumerate(rows):
            r[1], r[2] = repr(x + eps * (k % 2)), repr(y + eps * ((k // 2) % 2))
        write_csv(d / "landmarks.csv", h, rows)
    return m


def tiny_step(d: Path) -> None:
    h, rows = read_csv(d / "commands.csv")
    k = len(rows) // 2
    rows[k][0] = repr(float(rows[k + 1][0]) - 1e-9)
    write_csv(d / "commands.csv", h, rows)


def big_gap(gap: float, at: float = 90.0):
    def m(d: Path):
        for f in ("commands.csv", "observations.csv", "truth.csv"):
            h, rows = read_csv(d / f)
            for r in rows:
                if float(r[0]) >= at:
                    r[0] = repr(float(r[0]) + gap)
            write_csv(d / f, h, rows)
    return m


def bearing_flip(n: int):
    def m(d: Path):
        h, rows = read_csv(d / "observations.csv")
        i = h.index("bearing")
        idx = [k for k, r in enumerate(rows) if r[i] != ""]
        for j in range(1, n + 1):
            k = idx[int(j * len(idx) / (n + 1))]
            b = float(rows[k][i]) + math.pi
            rows[k][i] = repr(math.atan2(math.sin(b), math.cos(b)))
        write_csv(d / "observations.csv", h, rows)
    return m


def dup_id(d: Path) -> None:
    h, rows = read_csv(d / "landmarks.csv")
    rows[1][0] = rows[0][0] + ".0"
    write_csv(d / "landmarks.csv", h, rows)


# ------------------------------------------------------------------------------------------------- bad model files
# Each maker takes the Bench (for the clean models) and returns the file's bytes.
def raw(data: bytes):
    return lambda b: data


def set_in(keys: tuple, value=None, drop: bool = False):
    """The clean Aibo model with the entry at ``keys`` (None: the first key) set to ``value`` or removed; NaN is
    written as NaN."""
    def make(b):
        m = copy.deepcopy(b.base("aibo"))
        parent = m
        for k in keys[:-1]:
            parent = parent[next(iter(parent)) if k is None else k]
        last = next(iter(parent)) if keys[-1] is None else keys[-1]
        if drop:
            del parent[last]
        else:
            parent[last] = value
        return json.dumps(m).encode()
    return make


def velocity_literal(literal: str):
    """The clean Aibo model with the first action's vx written as the JSON text ``literal``."""
    def make(b):
        good = b.base("aibo")
        vel = good["action_model"]["velocities"]
        a0 = next(iter(vel))
        txt = json.dumps(good)
        new = txt.replace(f'"{a0}": {json.dumps(vel[a0])}', f'"{a0}": [{literal}, {json.dumps(vel[a0][1:])[1:]}', 1)
        if new == txt:
            raise RuntimeError(f"velocity of action {a0} not found in the clean model's text")
        return new.encode()
    return make


FIRST_VELOCITY = ("action_model", "velocities", None)      # the first action's
BAD_MODELS = {                                             # label: maker; each must be refused
    "JSON list": raw(b"[1, 2, 3]\n"),
    "binary bytes": raw(bytes(range(256)) * 4),
    "100000 nested lists": raw(b"[" * 100000 + b"]" * 100000),
    "reading_sigma 0": set_in(("sensor_model", "reading_sigma"), 0.0),
    "bearing_sigma -0.5": set_in(("sensor_model", "bearing_sigma"), -0.5),
    "motion_noise[0] -0.01": set_in(("motion_noise", 0), -0.01),
    "NaN velocity": set_in((*FIRST_VELOCITY, 0), float("nan")),
}
MORE_BAD_MODELS = {                                        # label: (maker, expected exit: '2' or '0or2' if sane)
    "velocity 1e400 (inf)": (velocity_literal("1e400"), "2"),
    "reading_sigma 1e-320": (set_in(("sensor_model", "reading_sigma"), 1e-320), "0or2"),
    "reading_sigma 1e300": (set_in(("sensor_model", "reading_sigma"), 1e300), "0or2"),
    "reading_sigma as string": (set_in(("sensor_model", "reading_sigma"), "1.0"), "2"),
    "reading_poly [1e308,...]": (set_in(("sensor_model", "reading_poly"), [1e308, 1e308, 0, 0]), "0or2"),
    "empty file": (raw(b""), "2"),
    "{} (empty object)": (raw(b"{}"), "2"),
    "velocities missing one action": (set_in(FIRST_VELOCITY, drop=True), "0or2"),
    "velocity of 2 numbers": (set_in(FIRST_VELOCITY, [0.1, 0.2]), "2"),
    "floor (command_poly) model for an aibo log": (lambda b: b.base_file("floor").read_bytes(), "0or2"),
}


# ------------------------------------------------------------------------------------------------- the runner
class Bench:
    """The work directory, the clean logs and models (made on first use), and the results."""

    def __init__(self, work: Path, select: list[str], json_out: str | None):
        self.work, self.select, self.json_out = work, select, json_out
        self.results: list[dict] = []
        self._base: dict[str, dict] = {}

    def selected(self, name: str) -> bool:
        return not self.select or any(s in name for s in self.select)

    def sh(self, cmd: list[str], user: str | None = None):
        """Run ``cmd`` in the work directory: (exit code or None after a timeout, stdout, stderr, seconds)."""
        if user:
            cmd = ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups", *cmd]
        t0 = time.time()
        p = subprocess.Popen(cmd, cwd=self.work, env=dict(ENV, HOME="/tmp") if user else ENV, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, start_new_session=True, preexec_fn=_cap_memory)
        try:
            out, err = p.communicate(timeout=TIMEOUT)
            rc = p.returncode
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)            # the session started for this run only
            out, err = p.communicate()
            rc = None
        return rc, out.decode(errors="replace"), err.decode(errors="replace"), time.time() - t0

    def setup(self, *args: str) -> None:
        rc, _, err, _ = self.sh(cli(*args))
        if rc != 0:
            raise SystemExit(f"setup failed (exit {rc}): casm-graph {shlex.join(args)}\n{err[-2000:]}")

    def log(self, kind: str) -> str:
        """The clean log of ``kind`` (aibo, floor), simulated on first use."""
        rel = f"logs/{kind}"
        if not (self.work / rel / "commands.csv").is_file():
            self.setup("simulate", rel, "--minutes", "3", "--seed", "0", *SIMULATE[kind])
        return rel

    def base_file(self, kind: str) -> Path:
        """model.json of the clean log's calibration (kind: aibo, floor, aibo_graph-em, aibo_ekfs-em)."""
        log_kind, _, method = kind.partition("_")
        out = self.work / f"base_{kind}"
        if not (out / "model.json").is_file():
            self.setup("calibrate", self.log(log_kind), "--out", out.name, "--quiet",
                       *(["--method", method] if method else []))
            m = json.loads((out / "model.json").read_text())["sensor_model"]
            print(f"clean {kind}: reading_sigma={m['reading_sigma']:.4g} bearing_sigma={m['bearing_sigma']:.4g}",
                  file=sys.stderr, flush=True)
        return out / "model.json"

    def base(self, kind: str) -> dict:
        if kind not in self._base:
            self._base[kind] = json.loads(self.base_file(kind).read_text())
        return self._base[kind]

    def measured(self) -> None:
        """measured/sensor.csv and actions.csv for compare, from the simulator's truth."""
        meas = self.work / "measured"
        if meas.is_dir():
            return
        truth = json.loads((self.work / self.log("aibo") / "truth_model.json").read_text())
        c = truth["sensor_model"]["reading_poly_best_cubic"]
        meas.mkdir()
        write_csv(meas / "sensor.csv", ["distance", "reading"],
                  [[f"{d:.2f}", f"{sum(ci * d ** i for i, ci in enumerate(c)):.4f}"]
                   for d in [1.5, 2.0, 2.5, 3.0, 3.5, 4.0]])
        write_csv(meas / "actions.csv", ["action", "vx", "vy", "w"],
                  [[a, *map(str, v)] for a, v in truth["action_model"]["velocities"].items()])

    def make_log(self, name: str, kind: str, mutate) -> str:
        d = self.work / "logs" / name
        if d.exists():
            shutil.rmtree(d)
        shutil.copytree(self.work / self.log(kind), d)
        mutate(d)
        return f"logs/{name}"

    def case(self, name: str, args: list[str], out: str | None, expect: str = "0or2", check=None,
             base: str | None = None, pre=None, user: str | None = None, protect=(), note: str = "") -> None:
        """Run one case and judge it.

        expect: '0or2' (either, if well formed), '2' (must be refused), '0' (must succeed). check(rc, outdir) ->
        problems of this case. base: the clean model (kind) an exit-0 model is compared with. protect: inputs
        (relative to the work directory) that must be unchanged whatever happens.
        """
        if not self.selected(name):
            return
        work = self.work
        outp = work / out if out else None
        cmd = ("setpriv --reuid=%s --regid=%s --clear-groups " % (user, user) if user else "") + shlex.join(cli(*args))
        try:
            if pre:
                pre()
        except Skip as e:
            self.record(dict(case=name, rc=None, first="", nlines=0, verdict=f"SKIP: {e}", secs=0.0,
                             cmd=f"cd {work} && {cmd}", model="", note=note))
            return
        before = snapshot(outp) if outp else None
        prot_before = {p: snapshot(work / p) for p in protect}
        rc, _, se, secs = self.sh(cli(*args), user=user)
        lines = [ln for ln in se.splitlines() if ln.strip()]
        first = lines[0] if lines else ""
        probs = []
        if rc is None:
            probs.append(f"timeout after {TIMEOUT}s")
        elif rc not in (0, 2):
            probs.append(f"exit {rc}")
        stray = [ln for ln in lines if not ln.startswith("casm-graph:")]
        if "Traceback" in se or stray:
            probs.append("traceback/numpy/LAPACK or other stray text on stderr: " + repr((stray or lines)[0][:120]))
        if rc == 2 and len(lines) != 1:
            probs.append(f"{len(lines)} stderr lines")
        if expect == "2" and rc == 0:
            probs.append("accepted (must be refused, exit 2)")
        if expect == "0" and rc == 2:
            probs.append("refused (must be accepted)")
        if outp is not None and rc != 0:
            after = snapshot(outp)
            if after != before:
                probs.append(f"output changed after failure: {before[0]} -> {after[0]}"
                             + (f" ({len(after[1])} entries)" if after[0] == "dir" else ""))
        for p, s in prot_before.items():
            if snapshot(work / p) != s:
                probs.append(f"input {p} modified/removed")
        model_info = ""
        if rc == 0 and outp is not None:
            missing = [f for f in EXPECTED.get(args[0], []) if not (outp / f).is_file()]
            if missing:
                probs.append(f"partial output, missing {missing}")
            for f in sorted(outp.glob("*.json")):
                try:
                    j = strict_json(f)
                except (ValueError, RecursionError) as e:
                    probs.append(f"{f.name}: {e}")
                    continue
                if f.name == "model.json" and isinstance(j, dict):
                    probs += model_problems(j, self.base(base) if base else None)
                    sm, fit = j.get("sensor_model") or {}, j.get("fit") or {}
                    model_info = (f"rs={sm.get('reading_sigma')!s:.6} bs={sm.get('bearing_sigma')!s:.6} "
                                  f"conv={fit.get('converged')} "
                                  f"pruned={fit.get('outliers_pruned', fit.get('outliers_set_aside'))}")
            tr = outp / "trajectory.csv"
            if tr.is_file() and re.search(r"\b(nan|inf)", tr.read_text(), re.I):
                probs.append("NaN/inf in trajectory.csv")
        if check and rc is not None:
            probs += check(rc, outp) or []
        if probs and rc == 0 and "conv=False" in model_info:
            probs.append("[model.json says converged=false and a warning was printed]")
        self.record(dict(case=name, rc=rc, first=first[:220], nlines=len(lines),
                         verdict="OK" if not probs else "FAIL: " + "; ".join(probs), secs=round(secs, 1),
                         cmd=f"cd {work} && {cmd}", model=model_info, note=note))

    def record(self, r: dict) -> None:
        self.results.append(r)
        print(f"[{r['secs']:5.1f}s] {r['case']}: rc={r['rc']} lines={r['nlines']} {r['first'][:150]!r}\n"
              f"      -> {r['verdict']} {r['model']}", file=sys.stderr, flush=True)
        if self.json_out:
            Path(self.json_out).write_text(json.dumps(self.results, indent=1, ensure_ascii=False))

    def cal(self, name: str, kind: str, mutate, expect="0or2", check=None, extra=(), base=None, note="") -> None:
        """calibrate on a mutated copy of the clean ``kind`` log."""
        if not self.selected(name):
            return
        slug = re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_")[:48]
        log = self.make_log(slug, kind, mutate)
        self.case(name, ["calibrate", log, "--out", f"out/{slug}", "--quiet", *extra], f"out/{slug}",
                  expect=expect, check=check, base=base or kind, protect=[log], note=note)


# ------------------------------------------------------------------------------------------------- checks
def similar_to_base(b: Bench, kind: str, tol: float):
    """An exit-0 model's sigmas within 1 +- tol of the clean model's."""
    def chk(rc, outp):
        if rc != 0 or not (outp / "model.json").is_file():
            return []
        m, m0 = json.loads((outp / "model.json").read_text()), b.base(kind)
        probs = []
        for key in ("reading_sigma", "bearing_sigma"):
            s, s0 = m["sensor_model"].get(key), m0["sensor_model"].get(key)
            if s and s0 and not 1 - tol <= s / s0 <= 1 + tol:
                probs.append(f"{key} {s:.4g} vs clean {s0:.4g} ({s / s0:.3g}x)")
        return probs
    return chk


def big_ids_check(b: Bench, kind: str):
    """Ids 2^53 and 2^53+1 stay two landmarks: accepted, close to clean, one offset each."""
    base_chk = similar_to_base(b, kind, 0.02)

    def chk(rc, outp):
        if rc == 2:
            return ["refused: the two ids were conflated (must stay distinct)"]
        if rc != 0 or not (outp / "model.json").is_file():
            return []
        probs = base_chk(rc, outp)
        effects = json.loads((outp / "model.json").read_text()).get("effects", {})
        if "landmark_offset" in effects:
            for v in BIG.values():
                if f"dx_{v}" not in json.dumps(effects):
                    probs.append(f"effects lack dx_{v} (ids conflated/rounded): "
                                 + ",".join(k for k in effects["landmark_offset"] if k.startswith("dx")))
        return probs
    return chk


# ------------------------------------------------------------------------------------------------- the cases
def issue_cases(b: Bench) -> None:
    """The cases of issue 23 (A-E)."""
    work = b.work
    # A: accepted, then crashed
    for kind in ("aibo", "floor"):
        b.cal(f"A1 {kind}: only 3 commands (first 3 rows)", kind, keep_commands(lambda n: [0, 1, 2]))
        b.cal(f"A1b {kind}: only 3 commands spanning the log", kind,
              keep_commands(lambda n: [0, n // 3, 2 * n // 3]))
    b.cal("A2 aibo: an action that runs one step only", "aibo", cell("commands.csv", 300, "action", "99"))
    for kind in ("aibo", "floor"):
        b.cal(f"A3 {kind}: all times x 1e300", kind, scale_times(1e300))
        b.cal(f"A4 {kind}: all times x 1e-300", kind, scale_times(1e-300))
        b.cal(f"A5 {kind}: landmark 0 at x=1e300", kind, cell("landmarks.csv", 0, "x", "1e300"))
        b.cal(f"A6 {kind}: one reading = 1e300", kind, cell("observations.csv", 10, "reading", "1e300"))
    # B: garbage that exited 0
    for kind in ("aibo", "floor"):
        b.cal(f"B2 {kind}: one observation only", kind, first_sightings(1))
        b.cal(f"B3 {kind}: all landmarks at one place", kind, landmarks_one_place)
        b.cal(f"B4 {kind}: landmark ids 2^53 and 2^53+1", kind, big_ids, check=big_ids_check(b, kind))
    b.cal("B4e aibo: ids 2^53, 2^53+1 with --effect landmark_offset", "aibo", big_ids,
          check=big_ids_check(b, "aibo"), extra=["--effect", "landmark_offset"])
    refuse = [
        ("B5a aibo: '1_350' in landmarks.x", "aibo", cell("landmarks.csv", 0, "x", "1_350")),
        ("B5b aibo: '18_8' in observations.reading", "aibo", cell("observations.csv", 0, "reading", "18_8")),
        ("B5c aibo: '2_5' in commands.action", "aibo", cell("commands.csv", 0, "action", "2_5")),
        ("B5d aibo: '0_0' as landmark id in landmarks.csv", "aibo", cell("landmarks.csv", 0, "landmark", "0_0")),
        ("B5e floor: '0_4' in commands.v", "floor", cell("commands.csv", 0, "v", "0_4")),
        ("B6a aibo: Arabic-Indic '١٨' in observations.reading", "aibo", cell("observations.csv", 0, "reading", "١٨")),
        ("B6b aibo: Arabic-Indic '٢٥' in commands.action", "aibo", cell("commands.csv", 0, "action", "٢٥")),
        ("B6c aibo: Arabic-Indic '٠' as landmark id", "aibo", cell("landmarks.csv", 0, "landmark", "٠")),
        ("B6d aibo: Arabic-Indic '٠' in commands.t row 1", "aibo", cell("commands.csv", 0, "t", "٠")),
        ("B6e floor: full-width '４' in observations.reading", "floor", cell("observations.csv", 0, "reading", "４")),
        ("B6f floor: Arabic-Indic '١٢' in landmarks.y", "floor", cell("landmarks.csv", 0, "y", "١٢")),
    ]
    for name, kind, m in refuse:
        b.cal(name, kind, m, expect="2")

    # C: the output directory
    def cal_out(name, out, expect="2", extra=(), pre=None, user=None, log=None, protect=None, note="", check=None):
        def setup():
            b.log("aibo")
            if pre:
                pre()
        b.case(name, ["calibrate", log or "logs/aibo", "--out", out, "--quiet", *extra], out, expect=expect,
               pre=setup, user=user, protect=protect or ["logs/aibo"], note=note, check=check, base="aibo")

    cal_out("C1 --out \"\"", "", check=lambda rc, o: ["wrote into the cwd"] if (work / "model.json").exists() else [])

    def a_file():
        (work / "afile.txt").write_text("precious\n")
    cal_out("C2 --out is an existing file", "afile.txt", pre=a_file)
    cal_out("C2f --out is an existing file, --force", "afile.txt", pre=a_file, extra=["--force"],
            note="--force replacing a regular file by a run directory is a judgement call")

    def read_only(immutable=False):
        def p():
            d = work / "ro"
            if d.exists():
                unfreeze(d)
                d.chmod(0o755)
                shutil.rmtree(d)
            d.mkdir()
            d.chmod(0o555)
            if immutable:
                try:
                    r = subprocess.run(["chattr", "+i", str(d)], capture_output=True, text=True, check=False)
                except FileNotFoundError:
                    raise Skip("chattr not found") from None
                if r.returncode:
                    raise Skip(f"chattr +i not possible here: {r.stderr.strip() or r.returncode}")
        return p
    cal_out("C3a --out in chmod 555 dir (as root)", "ro/run", expect="0or2", pre=read_only(),
            note="chmod 555 does not stop root: run as root, exit 0 is expected")
    try:
        cal_out("C3b --out in immutable dir (chattr +i, root)", "ro/run", pre=read_only(immutable=True))
    finally:
        unfreeze(work / "ro")

    def as_nobody():
        work.chmod(0o755)
        for p in work.rglob("*"):
            try:
                p.chmod(0o755 if p.is_dir() else 0o644)
            except OSError:
                pass
        read_only()()
        try:
            rc, _, err, _ = b.sh([sys.executable, "-c", "import casm_graph.cli; open('logs/aibo/commands.csv')"],
                                 user=NOBODY)
        except FileNotFoundError:
            raise Skip("setpriv not found") from None
        if rc != 0:
            last = ([ln for ln in err.splitlines() if ln.strip()] or [f"exit {rc}"])[-1]
            raise Skip(f"cannot run as user {NOBODY} here: {last[:160]}")
    cal_out("C3c --out in chmod 555 dir, run as nobody", "ro/run", pre=as_nobody, user=NOBODY)

    def nonempty():
        d = work / "nonempty"
        d.mkdir(exist_ok=True)
        (d / "keep.txt").write_text("keep\n")
    cal_out("C4 --out non-empty without --force", "nonempty", pre=nonempty)

    def copy_log():
        d = work / "logs" / "aibo_c5"
        if d.exists():
            shutil.rmtree(d)
        shutil.copytree(work / "logs" / "aibo", d)

    def link():
        copy_log()
        lk = work / "loglink"
        if lk.is_symlink() or lk.exists():
            lk.unlink()
        lk.symlink_to(work / "logs" / "aibo_c5")

    def parent():
        d = work / "parent"
        if d.exists():
            shutil.rmtree(d)
        d.mkdir()
        shutil.copytree(work / "logs" / "aibo", d / "aibo")
    c5 = dict(log="logs/aibo_c5", protect=["logs/aibo_c5"])
    cal_out("C5a --out = log dir", "logs/aibo_c5", pre=copy_log, **c5)
    cal_out("C5b --out = log dir, --force", "logs/aibo_c5", extra=["--force"], pre=copy_log, **c5)
    cal_out("C5c --out = log dir spelled 'LOG/.', --force", "logs/aibo_c5/.", extra=["--force"], pre=copy_log, **c5)
    cal_out("C5d --out = symlink to log dir, --force", "loglink", extra=["--force"], pre=link, **c5)
    cal_out("C5e --out = parent of log dir, --force", "parent", extra=["--force"], pre=parent, log="parent/aibo",
            protect=["parent/aibo"])

    def run_copy():
        d = work / "RUN"
        if d.exists():
            shutil.rmtree(d)
        shutil.copytree(b.base_file("aibo").parent, d)
    for force in ([], ["--force"]):
        b.case(f"C6 uncertainty --out RUN (RUN holds calibrate output){', --force' if force else ''}",
               ["uncertainty", "logs/aibo", "--model", "RUN/model.json", "--out", "RUN", "--quiet", "--max-steps", "30",
                *force], "RUN", expect="2", pre=run_copy, protect=["logs/aibo"])
    b.case("C6d diagnose --out RUN (RUN holds calibrate output), --force",
           ["diagnose", "logs/aibo", "--model", "RUN/model.json", "--out", "RUN", "--quiet", "--workers", "1",
            "--candidate", "lens_distortion", "--force"], "RUN", expect="2", pre=run_copy, protect=["logs/aibo"])

    # D: bad model files
    def control():
        b.base_file("aibo")
        b.measured()
    b.case("D0 compare, good model (control)", ["compare", "base_aibo/model.json", "--measured", "measured", "--out",
                                                 "out/D0"], "out/D0", expect="0", pre=control)
    for i, (label, make) in enumerate(BAD_MODELS.items()):
        model_cases(b, "D", f"m{i}", label, make, "2")

    # E: outliers
    for kind in ("aibo", "floor"):
        b.cal(f"E1 {kind}: one reading x 10000", kind, scale_reading(1, 1e4), expect="0",
              check=similar_to_base(b, kind, 0.25))
        b.cal(f"E5 {kind}: five readings x 10000", kind, scale_reading(5, 1e4), expect="0",
              check=similar_to_base(b, kind, 0.25))


def model_cases(b: Bench, tag: str, slot: str, label: str, make, expect: str) -> None:
    """diagnose, uncertainty and compare with one bad model file (written by ``make`` when first needed)."""
    mp = f"badmodels/{slot}/model.json"

    def write():
        f = b.work / mp
        if not f.is_file():
            data = make(b)
            b.log("aibo")
            b.measured()
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(data)
    runs = {"diagnose": ["diagnose", "logs/aibo", "--model", mp, "--quiet", "--workers", "1", "--candidate",
                         "lens_distortion"],
            "uncertainty": ["uncertainty", "logs/aibo", "--model", mp, "--quiet", "--max-steps", "30"],
            "compare": ["compare", mp, "--measured", "measured"]}
    for command, args in runs.items():
        out = f"out/{tag}{command[0]}{slot[1:]}"
        b.case(f"{tag} {command}: {label}", [*args, "--out", out], out, expect=expect, pre=write, protect=[mp],
               base="aibo" if command == "uncertainty" else None)


def probes(b: Bench) -> None:
    """Variants beside the issue's cases: just inside the loader's bounds, the fewest sightings, more outliers, other
    methods, downstream commands, more bad model files."""
    for kind in ("aibo", "floor"):
        b.cal(f"P1 {kind}: one reading = 1e8 (inside the 1e9 bound)", kind,
              cell("observations.csv", 10, "reading", "1e8"))
        b.cal(f"P2 {kind}: landmark 0 at x=9e5 (inside the 1e6 bound)", kind, cell("landmarks.csv", 0, "x", "9e5"))
        b.cal(f"P3 {kind}: all times x 5e7 (inside the 1e10 bound)", kind, scale_times(5e7))
        b.cal(f"P4 {kind}: all times x 1e-4 (step above 1e-6)", kind, scale_times(1e-4))
        b.cal(f"P5 {kind}: exactly 10 sightings spread over the log", kind, spread_obs(10))
        b.cal(f"P6 {kind}: landmarks within 2 cm of each other", kind, landmarks_near(0.02))
        b.cal(f"P7 {kind}: one command step of 1e-9 s", kind, tiny_step)
        b.cal(f"P8 {kind}: a 1e9 s gap mid-log", kind, big_gap(1e9))
        b.cal(f"P9 {kind}: 50 readings x 10000", kind, scale_reading(50, 1e4), expect="0",
              check=similar_to_base(b, kind, 0.25))
        b.cal(f"P10 {kind}: 5 readings x -10000", kind, scale_reading(5, -1e4), expect="0",
              check=similar_to_base(b, kind, 0.25))
        b.cal(f"P11 {kind}: 5 bearings flipped by pi", kind, bearing_flip(5), expect="0",
              check=similar_to_base(b, kind, 0.25))
    b.cal("P12 aibo: first 10 sightings only (one landmark, 0.3 s)", "aibo", first_sightings(10))
    b.cal("P13 aibo: landmark ids '0' and '0.0' (duplicate)", "aibo", dup_id, expect="2")
    for meth in ("graph-em", "ekfs-em"):
        for label, n in (("one reading", 1), ("five readings", 5)):
            b.cal(f"P14 aibo: {label} x 10000, --method {meth}", "aibo", scale_reading(n, 1e4), expect="0",
                  check=similar_to_base(b, f"aibo_{meth}", 0.25), extra=["--method", meth], base=f"aibo_{meth}")
    b.cal("P6b aibo: landmarks within 10 cm of each other", "aibo", landmarks_near(0.1))
    # downstream commands on the five-outlier log (E5 aibo) with its own model
    e5, log = "out/E5_aibo_five_readings_x_10000", "logs/E5_aibo_five_readings_x_10000"

    def needs_e5():
        if not (b.work / e5 / "model.json").is_file():
            raise Skip("needs the output of 'E5 aibo' (select it too)")
    b.case("P15 uncertainty on the five-outlier log", ["uncertainty", log, "--model", f"{e5}/model.json", "--out",
                                                       "out/P15", "--quiet", "--max-steps", "30"], "out/P15",
           expect="0", base="aibo", pre=needs_e5, check=similar_to_base(b, "aibo", 0.5))
    b.case("P16 diagnose on the five-outlier log", ["diagnose", log, "--model", f"{e5}/model.json", "--out", "out/P16",
                                                    "--quiet", "--workers", "1", "--candidate", "lens_distortion"],
           "out/P16", expect="0", pre=needs_e5)
    for i, (label, (make, expect)) in enumerate(MORE_BAD_MODELS.items()):
        model_cases(b, "PD", f"p{i}", label, make, expect)


def table(results: list[dict]) -> str:
    md = ["| case | exit | first stderr line | verdict |", "|---|---|---|---|"]
    for r in results:
        rc = "-" if r["verdict"].startswith("SKIP") else "timeout" if r["rc"] is None else r["rc"]
        first = r["first"].replace("|", "\\|")
        extra = f" ({r['model']})" if r["model"] else ""
        md.append(f"| {r['case']} | {rc} | {first} | {r['verdict'].replace('|', '/')}{extra} |")
    return "\n".join(md)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-k", action="append", default=[], metavar="TEXT", help="only cases whose name contains TEXT")
    ap.add_argument("--no-probes", action="store_true", help="only the issue's own cases")
    ap.add_argument("--work", default=None, help="new or empty directory for the logs and outputs (default: temporary)")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the results here")
    args = ap.parse_args(argv)
    if args.work:
        work = Path(args.work).resolve()
        if work.exists() and (not work.is_dir() or any(work.iterdir())):
            ap.error(f"--work {args.work}: not an empty directory")
        work.mkdir(parents=True, exist_ok=True)
    else:
        work = Path(tempfile.mkdtemp(prefix="casm_hostile_"))
    (work / "logs").mkdir()
    (work / "out").mkdir()
    b = Bench(work, args.k, args.json)
    try:
        issue_cases(b)
        if not args.no_probes:
            probes(b)
    finally:
        unfreeze(work / "ro")
    print(table(b.results))
    fails = sum(r["verdict"].startswith("FAIL") for r in b.results)
    skips = sum(r["verdict"].startswith("SKIP") for r in b.results)
    print(f"\n{len(b.results)} cases, {fails} FAIL" + (f", {skips} SKIP" if skips else ""))
    print(f"(logs and outputs in {work})", file=sys.stderr)
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
