"""Import one robot of the UTIAS MRCLAM dataset (Leung et al., IJRR 2011) as a log bundle.

The dataset's ``.dat`` files (whitespace separated, '#' header lines) become INTERFACE section 1:
commands.csv holds the commanded ``v,w`` rows (times made relative to the first command, rows
whose time does not advance dropped), observations.csv the sightings of mapped landmarks only
(barcodes of the other robots dropped; the range is the ``reading``), and truth.csv the Vicon
poses interpolated to the pose times. ``mrclam.json`` records where it came from.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from casm_graph.io.log import Log, LogError, placed, wrap
from casm_graph.io.log import write as write_bundle

WORKPLACE_DATA = Path("/work/shared/data/mrclam7")


def find_data() -> Path:
    """Where the run-7 files are: $CASM_MRCLAM, else a ``shared/data/mrclam7`` beside the working
    directory or the package (or any of their parents), else the workplace's shared copy."""
    if os.environ.get("CASM_MRCLAM"):
        return Path(os.environ["CASM_MRCLAM"])
    here = [Path.cwd().resolve(), Path(__file__).resolve().parent]
    for start in here:
        for d in (start, *start.parents):
            if (d / "shared" / "data" / "mrclam7" / "Robot1_Odometry.dat").is_file():
                return d / "shared" / "data" / "mrclam7"
    return WORKPLACE_DATA


def read_dat(path: Path, columns: int) -> np.ndarray:
    """The numeric rows of one dataset file as an (n, columns) array; LogError on anything else."""
    if not path.is_file():
        raise LogError(f"{path.name}: missing file (expected at {path})")
    try:
        a = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise LogError(f"{path.name}: not a table of numbers ({exc})") from None
    if a.shape[0] == 0:
        raise LogError(f"{path.name}: no data rows")
    if a.shape[1] < columns:
        raise LogError(f"{path.name}: {a.shape[1]} columns, expected {columns}")
    if not np.all(np.isfinite(a[:, :columns])):
        i = int(np.flatnonzero(~np.all(np.isfinite(a[:, :columns]), axis=1))[0])
        raise LogError(f"{path.name}, data row {i + 1}: NaN or inf where a number is required")
    return a[:, :columns]


def advancing(t: np.ndarray) -> np.ndarray:
    """Mask of rows whose time is later than every earlier row's (the first of equal times wins)."""
    prev = np.maximum.accumulate(np.concatenate([[-np.inf], t[:-1]]))
    return t > prev


def interpolate_poses(t_src: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 3) poses at times ``t`` by linear interpolation, heading unwrapped first."""
    th = np.unwrap(poses[:, 2])
    return np.column_stack([np.interp(t, t_src, poses[:, 0]), np.interp(t, t_src, poses[:, 1]),
                            wrap(np.interp(t, t_src, th))])


def load_robot(directory: str | Path, robot: int) -> tuple[Log, dict]:
    """One robot's files as a :class:`Log` (continuous ``v,w`` commands, truth at pose times), its steps placed as
    loading the imported bundle places them (:func:`casm_graph.io.log.placed`), and what was kept."""
    log, info = read_robot(directory, robot)
    return placed(log), info


def read_robot(directory: str | Path, robot: int) -> tuple[Log, dict]:
    """One robot's files as a :class:`Log`, a step per odometry row, and what was kept."""
    d = Path(directory)
    if not d.is_dir():
        raise LogError(f"{d}: not a directory (expected the MRCLAM dataset's .dat files)")
    if robot not in range(1, 6):
        raise LogError(f"--robot must be 1..5 (got {robot})")
    barcodes = read_dat(d / "Barcodes.dat", 2).astype(int)
    marks = read_dat(d / "Landmark_Groundtruth.dat", 3)
    odo = read_dat(d / f"Robot{robot}_Odometry.dat", 3)
    meas = read_dat(d / f"Robot{robot}_Measurement.dat", 4)
    gt = read_dat(d / f"Robot{robot}_Groundtruth.dat", 4)

    keep = advancing(odo[:, 0])
    odo = odo[keep]
    if len(odo) < 2:
        raise LogError(f"Robot{robot}_Odometry.dat: fewer than two rows with increasing times")
    epoch = float(odo[0, 0])
    t = odo[:, 0] - epoch

    lm_ids = marks[:, 0].astype(int)
    subject_of = {int(b): int(s) for s, b in barcodes}
    subject = np.array([subject_of.get(int(b), -1) for b in meas[:, 1]])
    is_mark = np.isin(subject, lm_ids)
    ot = meas[:, 0] - epoch
    step = float(np.median(np.diff(t)))
    inside = (ot >= t[0]) & (ot <= t[-1] + step)
    sel = np.flatnonzero(is_mark & inside)
    sel = sel[np.argsort(ot[sel], kind="stable")]

    gt = gt[advancing(gt[:, 0])]
    tg = gt[:, 0] - epoch
    t_pose = np.append(t, t[-1] + step)
    truth = np.column_stack([t_pose, interpolate_poses(tg, gt[:, 1:4], t_pose)])

    log = Log(landmark_ids=lm_ids, landmark_xy=marks[:, 1:3], t=t, action=None, controls=odo[:, 1:3],
              control_names=("v", "w"), obs_t=ot[sel], obs_landmark=subject[sel],
              obs_reading=meas[sel, 2], obs_bearing=wrap(meas[sel, 3]), truth=truth)
    info = {"source": "UTIAS MRCLAM", "directory": str(d), "robot": robot, "epoch": epoch,
            "command_rows": int(len(keep)), "command_rows_dropped": int((~keep).sum()),
            "measurements": int(len(meas)), "robot_sightings_dropped": int((~is_mark).sum()),
            "landmark_sightings_outside_commands": int((is_mark & ~inside).sum()),
            "observations": int(len(sel)),
            "truth_outside": bool(t_pose[0] < tg[0] or t_pose[-1] > tg[-1])}
    return log, info


def import_robot(directory: str | Path, robot: int, out: str | Path) -> tuple[Log, dict]:
    """Read one robot and write its bundle to ``out`` (nothing written when the input is bad); the log as
    :func:`load_robot` gives it."""
    raw, info = read_robot(directory, robot)
    d = write_bundle(raw, out)
    (Path(d) / "mrclam.json").write_text(json.dumps(info, indent=2))
    return placed(raw), info
