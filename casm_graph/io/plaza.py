"""Import the CMU Plaza 1 range-only data set (``Plaza1.mat``) as a log bundle: ``DR`` odometry as ``t,v,w``
commands, ``TD`` ranges as observations with the bearing empty, ``TL`` as landmarks, ``GT`` as truth."""
from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import scipy.io

from casm_graph.io.log import (
    MAX_HEADING,
    MAX_POSITION,
    MAX_READING,
    MAX_SPEED,
    MAX_TIME,
    Log,
    LogError,
    placed,
    wrap,
)
from casm_graph.io.log import write as write_bundle
from casm_graph.io.output import atomic_dir, checked_out

WORKPLACE_FILE = Path("/work/shared/data/plaza1/Plaza1.mat")

# variable -> its columns (for messages), as the data set's README lists them
COLUMNS = {"DR": ("time", "distance", "heading change"),
           "GT": ("time", "x", "y", "heading"),
           "TD": ("time", "robot", "beacon", "range"),
           "TL": ("beacon", "x", "y")}


def find_plaza() -> Path | None:
    """``Plaza1.mat``: $CASM_PLAZA, else ``shared/data/plaza1`` beside the working directory or the
    package (or any of their parents), else the workplace's shared copy; None when none exists."""
    if os.environ.get("CASM_PLAZA"):
        p = Path(os.environ["CASM_PLAZA"])
        return p if p.is_file() else None
    for start in (Path.cwd().resolve(), Path(__file__).resolve().parent):
        for d in (start, *start.parents):
            if (d / "shared" / "data" / "plaza1" / "Plaza1.mat").is_file():
                return d / "shared" / "data" / "plaza1" / "Plaza1.mat"
    return WORKPLACE_FILE if WORKPLACE_FILE.is_file() else None


def _first_line(exc: Exception) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def read_mat(path: Path) -> dict:
    """The variables of a MAT file; LogError when it is missing or not a readable MAT file."""
    if not path.is_file():
        raise LogError(f"{path}: missing file (expected the Plaza data set's .mat file)")
    try:
        return scipy.io.loadmat(str(path), appendmat=False)
    except MemoryError:
        raise
    except Exception as exc:  # scipy raises ValueError, MatReadError, NotImplementedError (v7.3), ...
        raise LogError(f"{path.name}: not a readable MAT file ({type(exc).__name__}: {_first_line(exc)})") from None


def variable(mat: dict, name: str, min_rows: int, source: str) -> np.ndarray:
    """``mat[name]`` as a finite float array of the README's column count and at least ``min_rows`` rows."""
    cols = COLUMNS[name]
    if name not in mat:
        have = ", ".join(k for k in mat if not k.startswith("__")) or "none"
        raise LogError(f"{source}: missing variable '{name}' (variables: {have})")
    a = mat[name]
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "biuf":
        kind = a.dtype if isinstance(a, np.ndarray) else type(a).__name__
        raise LogError(f"{source}, variable '{name}': not a numeric matrix ({kind})")
    if a.ndim != 2 or a.shape[1] != len(cols) or a.shape[0] < min_rows:
        raise LogError(f"{source}, variable '{name}': shape {a.shape}, expected ({'n' if min_rows < 2 else 'n >= 2'}, "
                       f"{len(cols)}) with columns {', '.join(cols)}")
    a = a.astype(float)
    bad = ~np.isfinite(a)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise LogError(f"{source}, variable '{name}', row {i + 1}, column {j + 1} ({cols[j]}): "
                       f"{a[i, j]} where a finite number is required")
    return a


def bounded(values: np.ndarray, bound: float, where: str, unit: str) -> None:
    """LogError naming the first value of magnitude above ``bound`` (a log bundle could not hold it)."""
    big = np.flatnonzero(np.abs(values) > bound)
    if len(big):
        raise LogError(f"{where}, row {big[0] + 1}: {values[big[0]]:g} is out of range (at most {bound:g}{unit})")


def increasing(t: np.ndarray, where: str) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = bad[0] + 1
        raise LogError(f"{where}, row {i + 1}, column 1 (time): times not increasing ({t[i - 1]:.6f} then {t[i]:.6f})")


def integer_ids(values: np.ndarray, where: str) -> np.ndarray:
    frac = np.flatnonzero((values != np.round(values)) | (np.abs(values) > 2.0 ** 53))
    if len(frac):
        raise LogError(f"{where}, row {frac[0] + 1}: beacon id {values[frac[0]]:g} is not an integer id")
    return values.astype(np.int64)


def read_plaza(path: str | Path, minutes: float | None = None) -> tuple[Log, dict]:
    """The data set as a :class:`Log` (continuous ``v,w`` commands, truth at pose times) and what was kept."""
    path = Path(path)
    src = path.name
    if minutes is not None and not (math.isfinite(minutes) and minutes > 0):
        raise LogError(f"--minutes must be a positive number (got {minutes})")
    mat = read_mat(path)
    dr = variable(mat, "DR", 2, src)
    gt = variable(mat, "GT", 2, src)
    td = variable(mat, "TD", 1, src)
    tl = variable(mat, "TL", 1, src)

    increasing(gt[:, 0], f"{src}, variable 'GT'")
    increasing(dr[:, 0], f"{src}, variable 'DR'")
    epoch = float(gt[0, 0])
    if dr[0, 0] <= epoch:
        raise LogError(f"{src}, variable 'DR', row 1: time {dr[0, 0]:.6f} is not after GT's first time {epoch:.6f} "
                       f"(where the first odometry interval begins)")
    if gt[-1, 0] < dr[-1, 0]:
        raise LogError(f"{src}, variable 'GT': ends at {gt[-1, 0]:.6f}, before the odometry ({dr[-1, 0]:.6f})")
    bounded(dr[:, 0] - epoch, MAX_TIME, f"{src}, variable 'DR', column 1 (time)", " s from GT's first time")

    rows = len(dr)
    ends = dr[:, 0] - epoch                         # each command's interval ends here
    kept = rows if minutes is None else int(np.searchsorted(ends, 60.0 * minutes, side="right"))
    if kept < 2:
        raise LogError(f"--minutes {minutes:g} keeps {kept} odometry row(s) of {src}; at least two are needed "
                       f"(the rows are {np.median(np.diff(ends)):.2f} s apart)")
    dr, ends = dr[:kept], ends[:kept]
    starts = np.concatenate([[0.0], ends[:-1]])
    dt = ends - starts
    controls = np.column_stack([dr[:, 1] / dt, dr[:, 2] / dt])
    for j, name in enumerate(("v (distance / interval)", "w (heading change / interval)")):
        bounded(controls[:, j], MAX_SPEED, f"{src}, variable 'DR', {name}", " m/s or rad/s")

    ids = integer_ids(tl[:, 0], f"{src}, variable 'TL', column 1 (beacon)")
    uniq, first = np.unique(ids, return_index=True)
    if len(uniq) != len(ids):
        dup = next(i for i in range(len(ids)) if i not in set(first))
        raise LogError(f"{src}, variable 'TL', row {dup + 1}: beacon id {ids[dup]} appears twice")
    for j in (1, 2):
        bounded(tl[:, j], MAX_POSITION, f"{src}, variable 'TL', column {j + 1} ({COLUMNS['TL'][j]})", " m")
        bounded(gt[:, j], MAX_POSITION, f"{src}, variable 'GT', column {j + 1} ({COLUMNS['GT'][j]})", " m")
    bounded(gt[:, 3], MAX_HEADING, f"{src}, variable 'GT', column 4 (heading)", " rad")

    beacon = integer_ids(td[:, 2], f"{src}, variable 'TD', column 3 (beacon)")
    unknown = np.flatnonzero(~np.isin(beacon, ids))
    if len(unknown):
        i = unknown[0]
        raise LogError(f"{src}, variable 'TD', row {i + 1}: beacon id {beacon[i]} is not in TL "
                       f"(TL has {sorted(ids.tolist())})")
    robots = np.unique(td[:, 1])
    if len(robots) != 1:
        raise LogError(f"{src}, variable 'TD', column 2 (robot): ranges from {len(robots)} robots "
                       f"({', '.join(f'{r:g}' for r in robots)}); one robot's data expected")
    bounded(td[:, 3], MAX_READING, f"{src}, variable 'TD', column 4 (range)", "")

    ot = td[:, 0] - epoch
    before = ot < 0.0
    late = ot > ends[-1]
    after_data, cut = (late, np.zeros_like(late)) if kept == rows else (np.zeros_like(late), late)
    sel = np.flatnonzero(~before & ~late)
    sel = sel[np.argsort(ot[sel], kind="stable")]
    if len(sel) == 0:
        span = f"the first {minutes:g} minutes" if minutes is not None else "the odometry's span"
        raise LogError(f"{src}: no range in {span} (0 to {ends[-1]:.1f} s after GT's first time)")

    pose_t = np.append(starts, starts[-1] + float(np.median(dt)))
    at = np.append(starts, ends[-1]) + epoch         # the last pose is where the last interval ends
    th = np.unwrap(gt[:, 3])
    truth = np.column_stack([pose_t, np.interp(at, gt[:, 0], gt[:, 1]), np.interp(at, gt[:, 0], gt[:, 2]),
                             wrap(np.interp(at, gt[:, 0], th))])

    log = Log(landmark_ids=ids, landmark_xy=tl[:, 1:3], t=starts, action=None, controls=controls,
              control_names=("v", "w"), obs_t=ot[sel], obs_landmark=beacon[sel], obs_reading=td[sel, 3],
              obs_bearing=np.full(len(sel), np.nan), truth=truth)
    offset = mat.get("init_heading_offset")
    info = {"source": "CMU Plaza 1 (range-only)", "file": str(path), "epoch": epoch,
            "minutes": minutes, "odometry_rows": rows, "command_steps": kept,
            "ranges": len(td), "observations": len(sel),
            "ranges_before_first_pose_dropped": int(before.sum()),
            "ranges_after_odometry_dropped": int(after_data.sum()),
            "ranges_after_minutes_cut": int(cut.sum()),
            "robot": float(robots[0]),
            "init_heading_offset": float(offset.ravel()[0])
            if isinstance(offset, np.ndarray) and offset.dtype.kind in "biuf" and offset.size == 1 else None,
            "convention": "command i holds from the previous DR row's time (GT's first time for i = 0) to DR "
                          "row i's time; times are seconds after GT's first time (epoch)"}
    return log, info


def drops(info: dict) -> list[str]:
    """One line per kind of range that had to be dropped (none when every range was kept)."""
    out = []
    if info["ranges_before_first_pose_dropped"]:
        out.append(f"{info['ranges_before_first_pose_dropped']} range(s) before the first pose (GT's first time) dropped")
    if info["ranges_after_odometry_dropped"]:
        out.append(f"{info['ranges_after_odometry_dropped']} range(s) after the last odometry row dropped")
    return out


def _tell(info: dict) -> None:
    for line in drops(info):
        print(f"casm-graph: warning: {Path(info['file']).name}: {line}", file=sys.stderr)


def load_plaza(path: str | Path, minutes: float | None = None) -> Log:
    """The data set (its first ``minutes`` when given) as a :class:`Log` with truth, its steps placed as loading the
    imported bundle places them (:func:`casm_graph.io.log.placed`); drops told on stderr."""
    log, info = read_plaza(path, minutes)
    _tell(info)
    return placed(log)


def import_plaza(path: str | Path, out: str | Path, force: bool = False,
                 minutes: float | None = None) -> tuple[Log, dict]:
    """Write the bundle (and plaza.json) to ``out`` all or nothing; LogError, nothing written, on bad input."""
    checked_out(out, force, inputs=[path])
    log, info = read_plaza(path, minutes)
    _tell(info)
    with atomic_dir(out, force=force, inputs=[path]) as tmp:
        write_bundle(log, tmp)
        (Path(tmp) / "plaza.json").write_text(json.dumps(info, indent=2))
    return log, info
