"""Log bundles (INTERFACE section 1): load and validate a directory of CSV files, or write one.

Every problem with the input is reported as one :class:`LogError` naming file, row and column,
so the command line can print it and exit with status 2 before anything is written.
"""
from __future__ import annotations

import csv
import math
import re
import warnings
from dataclasses import dataclass, field, replace
from decimal import Decimal
from functools import cached_property
from pathlib import Path

import numpy as np


class LogError(ValueError):
    """Bad input: the message names the file, row and column at fault."""


@dataclass(frozen=True)
class Log:
    """One robot log: the map, the command per step, the observations and (optionally) the truth.

    Poses live at ``pose_times`` (the command times plus one final pose); observation ``i``
    belongs to pose ``obs_step[i]``.
    """

    landmark_ids: np.ndarray            # (L,) int
    landmark_xy: np.ndarray             # (L, 2)
    t: np.ndarray                       # (T,) command times
    action: np.ndarray | None           # (T,) int action ids, or None for continuous commands
    controls: np.ndarray | None         # (T, k) continuous commands, or None
    control_names: tuple[str, ...]      # ('v', 'w') or ('vx', 'vy', 'w') or ()
    obs_t: np.ndarray                   # (N,)
    obs_landmark: np.ndarray            # (N,) landmark ids
    obs_reading: np.ndarray             # (N,) NaN where not measured
    obs_bearing: np.ndarray             # (N,) NaN where not measured
    obs_pan: np.ndarray | None = None   # (N,) NaN where unknown; None when the column is absent
    attempted: dict[int, np.ndarray] = field(default_factory=dict)   # actions.csv, information only
    truth: np.ndarray | None = None     # (T+1, 4) t, x, y, theta at pose times, when known
    source: str | None = None           # the bundle's directory, when loaded from disk
    command_row: np.ndarray | None = None   # (T,) row of commands.csv each step holds, when rows were held over
    #                                         several steps (:func:`held_steps`, :func:`sighting_steps`); None: one
    #                                         step per row

    @property
    def steps(self) -> int:
        return len(self.t)

    @property
    def action_model_kind(self) -> str:
        """The kind of action model this log is calibrated with: ``table`` for discrete actions, ``command_poly``
        for continuous commands (the ``kind`` of :mod:`casm_graph.models.velocity_table` and
        :mod:`casm_graph.models.command_model`)."""
        return "table" if self.action is not None else "command_poly"

    # The derived arrays below are computed once per Log (a Log is never changed after it is built:
    # ``window``/``prune`` make new ones) and handed out read-only, so a caller that wants to change
    # one must copy it first; per-segment loops index them freely (issue 25: ``obs_step`` recomputed
    # on every access made the turn-alias scoring quadratic in the log's length).

    @cached_property
    def dt(self) -> np.ndarray:
        """Duration of each command step; the last step lasts the median step."""
        if len(self.t) == 1:
            return _frozen(np.array([1.0]))
        d = np.diff(self.t)
        return _frozen(np.append(d, np.median(d)))

    def in_median_steps(self, seconds) -> np.ndarray:
        """``seconds`` counted in steps of the log's median length: what a motion-noise level per step scales by
        (a random walk), so a one-second gap in a real robot's odometry counts as the hundred steps it spans."""
        return np.asarray(seconds, float) / float(np.median(self.dt))

    @cached_property
    def pose_times(self) -> np.ndarray:
        return _frozen(np.append(self.t, self.t[-1] + self.dt[-1]))

    @cached_property
    def obs_step(self) -> np.ndarray:
        """Index of the pose each observation belongs to (nearest pose time)."""
        return _frozen(nearest_index(self.pose_times, self.obs_t))

    @cached_property
    def landmark_index(self) -> np.ndarray:
        """Row of ``landmark_xy`` for each observation."""
        order = np.argsort(self.landmark_ids)
        pos = np.searchsorted(self.landmark_ids[order], self.obs_landmark)
        return _frozen(order[pos])

    @cached_property
    def action_ids(self) -> np.ndarray:
        """Sorted distinct action ids that were run."""
        return _frozen(np.unique(self.action) if self.action is not None else np.array([], int))

    @cached_property
    def channels(self) -> tuple[str, ...]:
        """The sensor channels this log measures at all: ('reading', 'bearing'), or one of them
        (a range-only or bearing-only sensor leaves the other column empty everywhere)."""
        return tuple(name for name, col in (("reading", self.obs_reading), ("bearing", self.obs_bearing))
                     if np.any(~np.isnan(col)))

    @cached_property
    def camera_pan(self) -> np.ndarray:
        """(N,) the camera's pan at each sighting: ``obs_pan``, 0 where not logged (a camera fixed to the body, whose
        image angle is the bearing)."""
        return _frozen(np.zeros(len(self.obs_t)) if self.obs_pan is None else np.nan_to_num(self.obs_pan))

    @property
    def held_commands(self) -> dict | None:
        """How commands.csv's rows were held over steps (:func:`held_steps`): rows, steps and the median step in s;
        None when each row is one step."""
        if self.command_row is None:
            return None
        return {"rows": int(self.command_row[-1]) + 1, "steps": self.steps, "step": float(np.median(self.dt))}

    def file_row(self, step: int) -> int:
        """The data row of commands.csv (1 = the first after the header) that step ``step`` runs."""
        return int(step if self.command_row is None else self.command_row[step]) + 1

    @property
    def minutes(self) -> float:
        return float(self.pose_times[-1] - self.pose_times[0]) / 60.0

    def window(self, t0: float, t1: float) -> "Log":
        """The part of the log with command times in [t0, t1)."""
        keep = (self.t >= t0) & (self.t < t1)
        if keep.sum() < 2:
            raise LogError(f"window [{t0}, {t1}) holds fewer than two command steps")
        idx = np.flatnonzero(keep)
        t_end = self.t[idx[-1]] + self.dt[idx[-1]]
        ok = (self.obs_t >= self.t[idx[0]]) & (self.obs_t <= t_end)
        truth = None
        if self.truth is not None:
            truth = self.truth[np.append(idx, idx[-1] + 1)]
        return replace(
            self,
            t=self.t[idx],
            action=None if self.action is None else self.action[idx],
            controls=None if self.controls is None else self.controls[idx],
            command_row=None if self.command_row is None else self.command_row[idx],
            obs_t=self.obs_t[ok], obs_landmark=self.obs_landmark[ok],
            obs_reading=self.obs_reading[ok], obs_bearing=self.obs_bearing[ok],
            obs_pan=None if self.obs_pan is None else self.obs_pan[ok],
            truth=truth,
        )


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` made read-only (a cached array shared by every caller)."""
    a.flags.writeable = False
    return a


def nearest_index(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index of the nearest element of the sorted ``grid`` for each ``x``."""
    i = np.clip(np.searchsorted(grid, x), 1, len(grid) - 1)
    left_closer = (x - grid[i - 1]) <= (grid[i] - x)
    return np.where(left_closer, i - 1, i)


def wrap(a):
    """Wrap angles to (-pi, pi]."""
    w = np.mod(np.asarray(a, dtype=float) + np.pi, 2 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


# --------------------------------------------------------------------------- reading CSV files

# Plain ASCII decimals only: Python's float() also takes '1_350', non-ASCII digits and 'infinity'.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", re.ASCII)
_INTEGER = re.compile(r"[+-]?[0-9]+(?:\.0*)?", re.ASCII)
_NAN = re.compile(r"[+-]?nan", re.ASCII | re.IGNORECASE)
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.ASCII | re.IGNORECASE)
_BLANK = " \t\r\n"
_INT64_MAX = 2 ** 63 - 1

# What the units allow (INTERFACE section 1): larger magnitudes are typos or wrong units.
MAX_TIME = 1e10             # s (Unix times of today are 1.7e9)
MAX_POSITION = 1e6          # m
MAX_READING = 1e9           # the sensor's unit
MAX_ANGLE = 2 * math.pi + 1e-6   # rad (bearing, pan: wrapped or in [0, 2 pi))
MAX_SPEED = 1e3             # m/s and rad/s
MAX_HEADING = 1e6           # rad (truth may be unwrapped)
MIN_MEDIAN_STEP = 1e-4      # s between commands (a command log at over 10 kHz is a scaled time column)
MAX_MEDIAN_STEP = 600.0     # s: commands held for ten minutes each are not a velocity log
MAX_GAP = 86400.0           # s: a day without commands is two logs
HELD_SPLIT = 2.0            # commands whose median step is this many sightings' frames long are held over frames
MAX_HELD_STEPS = 5_000_000  # steps such holding may make (46 hours at 30 Hz)
OFF_GRID = 0.01             # s: sightings a median of more than this from their nearest pose get poses of their own
ON_GRID = 1e-3             # s: a sighting this close to a pose time is at it


def _show(cell: str) -> str:
    """A cell quoted for a one-line message (long cells cut, control characters escaped)."""
    s = cell if len(cell) <= 40 else cell[:40] + "..."
    return f"'{s}'" if s.isprintable() else ascii(s)


class _Table:
    """The columns of one CSV file as strings, with the file name kept for error messages."""

    def __init__(self, path: Path):
        self.name = path.name
        if not path.is_file():
            raise LogError(f"{path.name}: missing file (expected at {path})")
        try:
            with path.open(newline="", encoding="utf-8-sig") as fh:
                rows = list(csv.reader(fh))
        except UnicodeDecodeError as exc:
            raise LogError(f"{path.name}: not a UTF-8 text file ({exc.reason})") from None
        except csv.Error as exc:
            raise LogError(f"{path.name}: not a readable CSV file ({exc})") from None
        rows = [r for r in rows if any(c.strip() for c in r)]
        if not rows:
            raise LogError(f"{path.name}: empty file (no header row)")
        self.header = [h.strip() for h in rows[0]]
        self.header[0] = self.header[0].lstrip("#").strip()     # numpy's savetxt writes its header as "# t,..."
        self.rows = rows[1:]
        for i, r in enumerate(self.rows, start=1):
            if len(r) < len(self.header):
                raise LogError(f"{self.name}, row {i}: {len(r)} cells but the header has "
                               f"{len(self.header)} columns")

    def __len__(self):
        return len(self.rows)

    def has(self, col: str) -> bool:
        return col in self.header

    def require(self, *cols: str) -> None:
        for c in cols:
            if c not in self.header:
                raise LogError(f"{self.name}: missing column {_show(c)} (header: {_header(self)})")

    def nonempty(self) -> None:
        if not self.rows:
            raise LogError(f"{self.name}: no data rows")

    def numbers(self, col: str, allow_empty: bool = False, bound: float | None = None,
                unit: str = "") -> np.ndarray:
        """Column as floats: plain ASCII decimals only (``_NUMBER``), finite and, with ``bound``, of
        magnitude at most ``bound``; empty cells are NaN when allowed, and so is a written NaN there (numpy's
        ``savetxt`` writes ``nan`` for a component not measured); anything else is an error."""
        j = self.header.index(col)
        out = np.empty(len(self.rows))
        for i, r in enumerate(self.rows):
            cell = r[j].strip(_BLANK)
            if cell == "" or (allow_empty and _NAN.fullmatch(cell)):
                if allow_empty:
                    out[i] = np.nan
                    continue
                raise LogError(f"{self.name}, row {i + 1}, column '{col}': empty cell where a number "
                               f"is required")
            if not _NUMBER.fullmatch(cell):
                if _NON_FINITE.fullmatch(cell):
                    raise LogError(f"{self.name}, row {i + 1}, column '{col}': {_show(cell)} is not a "
                                   f"finite number")
                raise LogError(f"{self.name}, row {i + 1}, column '{col}': {_show(cell)} is not a number "
                               f"(expected a plain ASCII decimal such as -12.5 or 3e-2)")
            v = float(cell)
            if not math.isfinite(v):
                raise LogError(f"{self.name}, row {i + 1}, column '{col}': {_show(cell)} is not a "
                               f"finite number (too large)")
            if bound is not None and abs(v) > bound:
                raise LogError(f"{self.name}, row {i + 1}, column '{col}': {_show(cell)} is out of range "
                               f"(|{col}| <= {bound:g}{unit} expected)")
            out[i] = v
        return out

    def integers(self, col: str) -> np.ndarray:
        """Column as exact integers (ids): ASCII digits with an optional sign (``7.0`` and ``7.0e+00`` allowed),
        parsed as int, never through float, and within int64."""
        j = self.header.index(col)
        out = np.empty(len(self.rows), np.int64)
        for i, r in enumerate(self.rows):
            cell = r[j].strip(_BLANK)
            where = f"{self.name}, row {i + 1}, column '{col}'"
            if cell == "":
                raise LogError(f"{where}: empty cell where a number is required")
            if _INTEGER.fullmatch(cell):
                v = int(cell.split(".")[0])
            elif _NUMBER.fullmatch(cell):          # 3.000000000000000000e+00: numpy's savetxt writes ids so
                d = Decimal(cell)
                if d.adjusted() > 19:            # int() of 1e999999999 would not end
                    raise LogError(_out_of_range(where, cell))
                if d != d.to_integral_value():
                    raise LogError(f"{where}: {_show(cell)} is not an integer")
                v = int(d)
            elif _NON_FINITE.fullmatch(cell):
                raise LogError(f"{where}: {_show(cell)} is not a finite number")
            else:
                raise LogError(f"{where}: {_show(cell)} is not a number (expected an integer id such as 7)")
            if not -_INT64_MAX <= v <= _INT64_MAX:
                raise LogError(_out_of_range(where, cell))
            out[i] = v
        return out


def _out_of_range(where: str, cell: str) -> str:
    return f"{where}: {_show(cell)} is out of range (ids must fit in 64 bits, |id| <= {_INT64_MAX})"


def _increasing(tab: _Table, t: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = bad[0] + 1
        raise LogError(f"{tab.name}, row {i + 1}, column 't': times not increasing "
                       f"({t[i - 1]:g} then {t[i]:g})")


def in_time_order(t: np.ndarray) -> np.ndarray | None:
    """The stable order that sorts observations.csv's rows by time, None when they already are (a generator that
    writes each landmark's sightings in turn); a RuntimeWarning names the first row out of order."""
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back) == 0:
        return None
    i = int(back[0]) + 1
    warnings.warn(f"observations.csv, row {i + 1}, column 't': time {t[i]:g} comes after {t[i - 1]:g}; "
                  f"the {len(t):,} rows are taken in time order", RuntimeWarning, stacklevel=3)
    return np.argsort(t, kind="stable")


def _plausible_step(tab: _Table, t: np.ndarray) -> None:
    """Times in seconds: a median command step far outside 0.1 ms-10 min, or a gap of more than a day, is wrong
    units, a scaled column or two logs in one (and would make the knot layout of a continuous log enormous)."""
    if len(t) > 1:
        step = float(np.median(np.diff(t)))
        if step < MIN_MEDIAN_STEP or step > MAX_MEDIAN_STEP:
            raise LogError(f"{tab.name}, rows 1-{len(t)}, column 't': the median step between rows is {step:.3g} s; "
                           f"times must be in seconds (a median step outside {MIN_MEDIAN_STEP:g}-{MAX_MEDIAN_STEP:g} s "
                           f"is not plausible)")
        i = int(np.argmax(np.diff(t)))
        if t[i + 1] - t[i] > MAX_GAP:
            raise LogError(f"{tab.name}, rows {i + 1}-{i + 2}, column 't': a gap of {t[i + 1] - t[i]:.3g} s between "
                           f"two commands (more than a day); split the log there into two")


def held_steps(t: np.ndarray, obs_t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(row of commands.csv of each step, the steps' times) when the commands change far more seldom than the
    sightings come (a log that writes a row only when the command changes): each row is held over steps of the
    sightings' frame (the median gap between distinct sighting times, leaving out gaps under half their 90th
    percentile: sightings of one frame stamped apart), the last one until the last sighting (a row
    written at a change says nothing of how long the last command ran), so that every sighting has a pose near its
    time. None when the rows already are that fine."""
    u = np.unique(obs_t)
    if len(t) < 2 or len(u) < 2:
        return None
    gaps = np.diff(u)
    frame = float(np.median(gaps[gaps >= 0.5 * np.quantile(gaps, 0.9)]))
    step = float(np.median(np.diff(t)))
    if frame <= 0 or step <= HELD_SPLIT * frame:
        return None
    d = np.append(np.diff(t), max(frame, float(u[-1] - t[-1])))
    n = np.maximum(1, np.rint(d / frame)).astype(int)
    if n.sum() > MAX_HELD_STEPS:
        raise LogError(f"commands.csv, rows 1-{len(t)}, column 't': a row every {step:.3g} s (median) held over the "
                       f"sightings' frame of {frame:.3g} s would make {n.sum():,} steps; write one row per control "
                       f"step, or split the log")
    rows = np.repeat(np.arange(len(t)), n)
    first = np.repeat(np.cumsum(n) - n, n)
    return rows, t[rows] + (np.arange(len(rows)) - first) * (d / n)[rows]


def sighting_steps(t: np.ndarray, obs_t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(step each new step continues, the steps' times) when the sightings lie off the steps' grid (a camera on its
    own clock): their median distance in time from the nearest pose is more than ``OFF_GRID``. Each distinct
    sighting time then starts a step of its own, under the command that holds there, so every sighting is seen
    from the pose of its time; taken to the nearest pose instead, a fixed phase reads as a camera latency and a
    drifting one as bearing noise growing with the turn rate. Sightings after the last command's median step keep
    the final pose. None when the sightings are on the grid."""
    if len(t) < 2 or len(obs_t) == 0:
        return None
    pose_t = np.append(t, t[-1] + float(np.median(np.diff(t))))
    if float(np.median(np.abs(obs_t - pose_t[nearest_index(pose_t, obs_t)]))) <= OFF_GRID:
        return None
    u = np.unique(obs_t)
    u = u[(u > t[0]) & (u < pose_t[-1]) & (np.abs(u - pose_t[nearest_index(pose_t, u)]) > ON_GRID)]
    times = np.union1d(t, u)
    if len(times) > MAX_HELD_STEPS:
        raise LogError(f"observations.csv: sightings at {len(u):,} times off the commands' grid would make "
                       f"{len(times):,} steps; write one command row per camera frame, or split the log")
    return np.searchsorted(t, times, side="right") - 1, times


def _truth_at_poses(truth: np.ndarray, t: np.ndarray) -> np.ndarray | None:
    """truth.csv at other times than the poses' (one per command step plus the final one): interpolated
    at the pose times when it covers them (the final pose, whose time is a median step after the last command's,
    may lie up to a step past the table's end and take its last row), else left out (it is information only,
    never fitted)."""
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    pose_t = np.append(t, t[-1] + step)
    tt = truth[:, 0]
    if (len(tt) < 2 or np.any(np.diff(tt) <= 0) or pose_t[0] < tt[0] or pose_t[-2] > tt[-1]
            or pose_t[-1] > tt[-1] + step):
        return None
    theta = np.interp(pose_t, tt, np.unwrap(truth[:, 3]))
    return np.column_stack([pose_t, np.interp(pose_t, tt, truth[:, 1]), np.interp(pose_t, tt, truth[:, 2]),
                            wrap(theta)])


def _header(tab: _Table) -> str:
    """The header row for a one-line message."""
    h = ",".join(tab.header)
    h = h if len(h) <= 200 else h[:200] + "..."
    return h if h.isprintable() else ascii(h)


def load(directory: str | Path) -> Log:
    """Read and validate a log bundle; raise :class:`LogError` on any bad input."""
    d = Path(directory)
    if not d.is_dir():
        raise LogError(f"{d}: not a directory (a log bundle is a directory of CSV files)")

    lm = _Table(d / "landmarks.csv")
    lm.require("landmark", "x", "y")
    lm.nonempty()
    ids = lm.integers("landmark")
    xy = np.column_stack([lm.numbers(c, bound=MAX_POSITION, unit=" m") for c in ("x", "y")])
    _, first = np.unique(ids, return_index=True)
    if len(first) != len(ids):
        dup = next(i for i in range(len(ids)) if i not in set(first))
        raise LogError(f"landmarks.csv, row {dup + 1}, column 'landmark': id {ids[dup]} appears twice")

    cm = _Table(d / "commands.csv")
    cm.require("t")
    cm.nonempty()
    t = cm.numbers("t", bound=MAX_TIME, unit=" s")
    _increasing(cm, t)
    _plausible_step(cm, t)
    action = controls = None
    names: tuple[str, ...] = ()
    if cm.has("action"):
        action = cm.integers("action")
    elif all(cm.has(c) for c in ("vx", "vy", "w")):
        names = ("vx", "vy", "w")
    elif all(cm.has(c) for c in ("v", "w")):
        names = ("v", "w")
    else:
        raise LogError(f"commands.csv: missing column 'action' (or continuous commands 'v,w' or "
                       f"'vx,vy,w'); header: {_header(cm)}")
    if names:
        controls = np.column_stack([cm.numbers(c, bound=MAX_SPEED, unit=" m/s or rad/s") for c in names])

    ob = _Table(d / "observations.csv")
    ob.require("t", "landmark", "reading", "bearing")
    ob.nonempty()
    ot = ob.numbers("t", bound=MAX_TIME, unit=" s")
    ol = ob.integers("landmark")
    known = set(ids.tolist())
    for i, k in enumerate(ol):
        if k not in known:
            raise LogError(f"observations.csv, row {i + 1}, column 'landmark': unknown landmark id "
                           f"{k} (landmarks.csv has {sorted(known)})")
    reading = ob.numbers("reading", allow_empty=True, bound=MAX_READING)
    bearing = ob.numbers("bearing", allow_empty=True, bound=MAX_ANGLE, unit=" rad")
    pan = ob.numbers("pan", allow_empty=True, bound=MAX_ANGLE, unit=" rad") if ob.has("pan") else None
    order = in_time_order(ot)
    if order is not None:
        ot, ol, reading, bearing = ot[order], ol[order], reading[order], bearing[order]
        pan = None if pan is None else pan[order]
    step = np.median(np.diff(t)) if len(t) > 1 else 1.0
    held = held_steps(t, ot)                 # the last row then holds until the last sighting: no bound after it
    out = (ot < t[0] - step / 2) | ((ot > t[-1] + 1.5 * step) & (held is None))
    if out.any():
        i = int(np.argmax(out))
        row = i if order is None else int(order[i])
        span = f"the commands' span, {t[0]:g} to {t[-1] + step:g} s"
        if out.all():
            raise LogError(f"observations.csv: every sighting lies outside {span} (row {row + 1}: time {ot[i]:g})")
        warnings.warn(f"observations.csv: {int(out.sum()):,} sighting(s) outside {span}, the first at row {row + 1} "
                      f"(time {ot[i]:g}), set aside", RuntimeWarning, stacklevel=2)
        keep = ~out
        ot, ol, reading, bearing = ot[keep], ol[keep], reading[keep], bearing[keep]
        pan = None if pan is None else pan[keep]
    if np.all(np.isnan(reading) & np.isnan(bearing)):
        raise LogError("observations.csv: every row has both 'reading' and 'bearing' empty")
    attempted: dict[int, np.ndarray] = {}
    if (d / "actions.csv").is_file():
        ac = _Table(d / "actions.csv")
        ac.require("action", "vx_cmd", "vy_cmd", "w_cmd")
        a_ids = ac.integers("action")
        cmd = np.column_stack([ac.numbers(c, bound=MAX_SPEED, unit=" m/s or rad/s")
                               for c in ("vx_cmd", "vy_cmd", "w_cmd")])
        attempted = {int(a): cmd[i] for i, a in enumerate(a_ids)}

    truth = None
    if (d / "truth.csv").is_file():
        tr = _Table(d / "truth.csv")
        tr.require("t", "x", "y", "theta")
        truth = np.column_stack([tr.numbers(c, bound=b, unit=u) for c, b, u in
                                 (("t", MAX_TIME, " s"), ("x", MAX_POSITION, " m"), ("y", MAX_POSITION, " m"),
                                  ("theta", MAX_HEADING, " rad"))])
    log = Log(landmark_ids=ids, landmark_xy=xy, t=t, action=action, controls=controls,
              control_names=names, obs_t=ot, obs_landmark=ol, obs_reading=reading, obs_bearing=bearing, obs_pan=pan,
              attempted=attempted, truth=None if truth is None or len(truth) != len(t) + 1 else truth,
              source=str(d))
    return placed(log, truth)


def placed(log: Log, truth: np.ndarray | None = None) -> Log:
    """``log`` (one step per row of commands.csv) with its steps where its sightings need them: rows held over the
    sightings' frame (:func:`held_steps`), then a step at each sighting time off the grid (:func:`sighting_steps`);
    ``log`` itself when neither applies. ``truth``: the (t, x, y, theta) table interpolated at the new pose times
    (default ``log.truth``)."""
    truth = log.truth if truth is None else truth
    t, row = log.t, None
    held = held_steps(t, log.obs_t)
    if held is not None:
        row, t = held
    off = sighting_steps(t, log.obs_t)
    if off is not None:
        step_row, t = off
        row = step_row if row is None else row[step_row]
    if row is None:
        if truth is not None and len(truth) != len(t) + 1:
            return replace(log, truth=_truth_at_poses(truth, t))
        return log
    return replace(log, t=t, action=None if log.action is None else log.action[row],
                   controls=None if log.controls is None else log.controls[row],
                   truth=None if truth is None else _truth_at_poses(truth, t), command_row=row)


# --------------------------------------------------------------------------- writing

def _fmt(x) -> str:
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    return "" if math.isnan(x) else repr(round(x, 9))


def _write_csv(path: Path, header: list[str], columns: list[np.ndarray]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in zip(*columns):
            w.writerow([_fmt(v) for v in row])


def write(log: Log, directory: str | Path) -> Path:
    """Write ``log`` as a bundle (creating the directory)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    _write_csv(d / "landmarks.csv", ["landmark", "x", "y"],
               [log.landmark_ids, log.landmark_xy[:, 0], log.landmark_xy[:, 1]])
    if log.action is not None:
        _write_csv(d / "commands.csv", ["t", "action"], [log.t, log.action])
    else:
        _write_csv(d / "commands.csv", ["t", *log.control_names],
                   [log.t, *log.controls.T])
    cols = ["t", "landmark", "reading", "bearing"]
    data = [log.obs_t, log.obs_landmark, log.obs_reading, log.obs_bearing]
    if log.obs_pan is not None:
        cols.append("pan")
        data.append(log.obs_pan)
    _write_csv(d / "observations.csv", cols, data)
    if log.attempted:
        ids = sorted(log.attempted)
        cmd = np.array([log.attempted[a] for a in ids])
        _write_csv(d / "actions.csv", ["action", "vx_cmd", "vy_cmd", "w_cmd"],
                   [np.array(ids), *cmd.T])
    if log.truth is not None:
        _write_csv(d / "truth.csv", ["t", "x", "y", "theta"], list(log.truth.T))
    return d
