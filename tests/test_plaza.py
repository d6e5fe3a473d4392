"""Issue 22: the CMU Plaza 1 importer (range-only radio beacons, `casm-graph import-plaza`).

The real file is found by ``plaza.find_plaza()`` ($CASM_PLAZA, else shared/data/plaza1/Plaza1.mat); the
tests on it are skipped when it is absent. The small and malformed files are built here.
"""
import csv
import json

import numpy as np
import pytest
import scipy.io

from casm_graph.cli import main
from casm_graph.graph.table import integrate
from casm_graph.io import plaza
from casm_graph.io.log import LogError, load, wrap

DATA = plaza.find_plaza()
needs_data = pytest.mark.skipif(DATA is None, reason="no Plaza1.mat (set CASM_PLAZA or put it in shared/data/plaza1)")


@pytest.fixture(scope="module")
def raw():
    return scipy.io.loadmat(str(DATA))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("plaza") / "plaza1"
    assert main(["import-plaza", str(DATA), "--out", str(out)]) == 0
    return out


def dead_reckon(log):
    """Poses integrating the bundle's commands from the true start, as the project reads them."""
    steps = np.column_stack([log.controls[:, 0] * log.dt, np.zeros(log.steps), log.controls[:, 1] * log.dt])
    return integrate(log.truth[0, 1:4], steps)


def row_starts(log):
    """The step where each row of commands.csv starts: the ranges lie off the odometry's 0.2-s grid, so loading
    the bundle starts a step at each range's time too (``io.log.sighting_steps``)."""
    return np.flatnonzero(np.diff(np.append(-1, log.command_row)))


def synthetic(n=60, seed=0) -> dict:
    """A small Plaza-like data set whose odometry is exact: GT composed from the DR increments."""
    rng = np.random.default_rng(seed)
    t = 100.0 + np.concatenate([[0.0], np.cumsum(rng.uniform(0.15, 0.25, n))])
    d, dth = rng.uniform(0.0, 0.2, n), rng.uniform(-0.1, 0.1, n)
    pose = [(1.0, 2.0, 3.0)]
    for k in range(n):
        x, y, th = pose[-1]
        pose.append((x + d[k] * np.cos(th), y + d[k] * np.sin(th), th + dth[k]))
    tl = np.array([[3.0, 10.0, 0.0], [7.0, -5.0, 8.0]])
    ot = np.concatenate([rng.uniform(t[0], t[-1], 20), [t[0] - 1.0, t[-1] + 1.0]])
    td = np.column_stack([ot, np.full(len(ot), 2.0), rng.choice([3.0, 7.0], len(ot)), rng.uniform(1, 20, len(ot))])
    return {"DR": np.column_stack([t[1:], d, dth]), "GT": np.column_stack([t, np.array(pose)]),
            "TD": td[rng.permutation(len(td))], "TL": tl, "init_heading_offset": np.zeros((1, 1))}


@needs_data
def test_rows_times_and_empty_bearings(bundle, raw):
    log = load(bundle)
    dr, gt, td, tl = raw["DR"], raw["GT"], raw["TD"], raw["TL"]
    assert log.control_names == ("v", "w") and log.action is None
    first = row_starts(log)
    assert len(first) == len(dr) == 9657 and len(log.obs_t) == len(td) == 3529
    assert np.array_equal(log.command_row[first], np.arange(len(dr)))
    assert sorted(log.landmark_ids.tolist()) == sorted(tl[:, 0].astype(int).tolist())
    assert log.truth.shape == (log.steps + 1, 4)
    # each range is seen from a pose of its own time: a step starts at each range time more than 1 ms off a row's
    assert np.abs(log.obs_t - log.pose_times[log.obs_step]).max() < 1e-3
    grid = np.append(log.t[first], log.t[first][-1] + 0.2)
    ranges = np.unique(log.obs_t)
    near = np.minimum(np.abs(ranges - grid[np.clip(np.searchsorted(grid, ranges), 0, len(grid) - 1)]),
                      np.abs(ranges - grid[np.clip(np.searchsorted(grid, ranges) - 1, 0, len(grid) - 1)]))
    assert log.steps == len(dr) + np.sum((near > 1e-3) & (ranges > 0)) == 13130
    t0 = gt[0, 0]
    # command i holds from DR row i-1's time (GT's first for i = 0) to DR row i's time
    assert log.t[0] == 0.0 and np.allclose(log.t[first][1:], dr[:-1, 0] - t0, atol=1e-6)
    moved = np.zeros((len(dr), 2))
    np.add.at(moved, log.command_row, log.controls * log.dt[:, None])
    assert np.allclose(moved[:-1], dr[:-1, 1:3], atol=1e-6)       # the last row lasts the log's final step
    assert np.allclose(log.truth[first, 1:3], gt[:-1, 1:3], atol=1e-6)
    # every range kept, sorted by time (two TD rows are out of order in the file)
    assert np.all(np.diff(log.obs_t) >= 0)
    order = np.argsort(td[:, 0], kind="stable")
    assert np.allclose(log.obs_t, td[order, 0] - t0, atol=1e-6)
    assert np.array_equal(log.obs_landmark, td[order, 2].astype(int))
    assert np.allclose(log.obs_reading, td[order, 3], atol=1e-6)
    assert np.all(np.isnan(log.obs_bearing))
    with (bundle / "observations.csv").open() as fh:
        assert all(row["bearing"] == "" for row in csv.DictReader(fh))
    info = json.loads((bundle / "plaza.json").read_text())
    assert info["ranges_before_first_pose_dropped"] == info["ranges_after_odometry_dropped"] == 0


@needs_data
def test_dead_reckoning_from_the_true_start(bundle, raw):
    """The commands integrated as the project reads them follow DRp's path length and GT's heading exactly.

    The README's 20 m RMS (45 m worst) drift is DRp's, not the commands': DRp's stored heading is GT's,
    but its positions were integrated along a heading that drifts ~0.02 rad/min away from it, whereas
    DR's heading changes equal GT's. The commands themselves drift to ~2 m RMS (4.4 m worst)."""
    log = load(bundle)
    first = row_starts(log)
    poses = dead_reckon(log)[first]
    truth = log.truth[first]
    gt, drp = raw["GT"], raw["DRp"]
    path = np.sum(np.hypot(*np.diff(drp[:-1, 1:3], axis=0).T))
    assert abs(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T)) - path) < 1e-3 * path
    assert np.max(np.abs(wrap(poses[:, 2] - truth[:, 3]))) < 1e-5
    err = np.hypot(*(poses[:, :2] - truth[:, 1:3]).T)
    rms = float(np.sqrt(np.mean(err ** 2)))
    assert 1.0 < rms < 4.0 and err.max() < 8.0                      # measured 1.97 m, 4.39 m
    drp_err = np.hypot(*(drp[:, 1:3] - gt[:, 1:3]).T)
    assert 18.0 < np.sqrt(np.mean(drp_err ** 2)) < 23.0 and 40.0 < drp_err.max() < 50.0   # 20.3 m, 44.8 m


@needs_data
def test_minutes_cut_and_force(raw, tmp_path, capsys):
    out = tmp_path / "two"
    assert main(["import-plaza", str(DATA), "--out", str(out), "--minutes", "2"]) == 0
    assert "ranges cut" in capsys.readouterr().out
    log = load(out)
    dr, gt, td = raw["DR"], raw["GT"], raw["TD"]
    ends = dr[:, 0] - gt[0, 0]
    kept = int(np.sum(ends <= 120.0))
    assert len(row_starts(log)) == kept and abs(log.minutes - 2.0) < 0.01
    ot = td[:, 0] - gt[0, 0]
    assert len(log.obs_t) == int(np.sum((ot >= 0) & (ot <= ends[kept - 1])))
    assert np.allclose(log.truth[row_starts(log)[-1], 1:3], gt[kept - 1, 1:3], atol=1e-6)
    direct = plaza.load_plaza(DATA, minutes=2)
    assert np.allclose(direct.t, log.t, atol=1e-6) and np.allclose(direct.controls, log.controls, atol=1e-6)
    assert np.allclose(direct.obs_t, log.obs_t, atol=1e-6) and np.allclose(direct.truth, log.truth, atol=1e-6)

    assert main(["import-plaza", str(DATA), "--out", str(out), "--minutes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err
    assert len(row_starts(load(out))) == kept
    assert main(["import-plaza", str(DATA), "--out", str(out), "--minutes", "1", "--force"]) == 0
    assert len(row_starts(load(out))) < kept


def test_synthetic_round_trip_reports_dropped_ranges(tmp_path, capsys):
    data = synthetic()
    scipy.io.savemat(tmp_path / "small.mat", data)
    out = tmp_path / "out"
    assert main(["import-plaza", str(tmp_path / "small.mat"), "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert "1 range(s) before the first pose" in cap.err and "1 range(s) after the last odometry row" in cap.err
    log = load(out)
    first = row_starts(log)
    assert len(first) == 60 and log.steps == 80 and len(log.obs_t) == 20 and np.all(np.isnan(log.obs_bearing))
    poses = dead_reckon(log)[first]   # exact odometry: the commands give GT back at each row's start, the positions
    #                                   up to the rows split at ranges' times (a turn begun inside the row)
    assert np.allclose(poses[:, :2], data["GT"][:-1, 1:3], atol=0.02)
    assert np.allclose(wrap(poses[:, 2] - data["GT"][:-1, 3]), 0.0, atol=1e-6)
    with pytest.raises(LogError, match="at least two"):
        plaza.load_plaza(tmp_path / "small.mat", minutes=0.001)


def _broken(data, name):
    d = dict(data)
    if name == "missing variable":
        del d["TD"]
    elif name == "wrong columns":
        d["DR"] = d["DR"][:, :2]
    elif name == "transposed":
        d["TL"] = d["TL"].T
    elif name == "no ranges":
        d["TD"] = np.zeros((0, 4))
    elif name == "text variable":
        d["GT"] = "ground truth"
    elif name == "NaN":
        d["GT"] = d["GT"].copy()
        d["GT"][3, 2] = np.nan
    elif name == "inf":
        d["TD"] = d["TD"].copy()
        d["TD"][5, 3] = np.inf
    elif name == "unknown beacon":
        d["TD"] = d["TD"].copy()
        d["TD"][0, 2] = 9.0
    elif name == "times repeat":
        d["DR"] = d["DR"].copy()
        d["DR"][4, 0] = d["DR"][3, 0]
    return d


BROKEN = {"missing variable": "missing variable 'TD'", "wrong columns": "variable 'DR': shape (60, 2)",
          "transposed": "variable 'TL': shape (3, 2)", "no ranges": "variable 'TD': shape",
          "text variable": "variable 'GT': not a numeric matrix", "NaN": "variable 'GT', row 4, column 3 (y)",
          "inf": "variable 'TD', row 6, column 4 (range)", "unknown beacon": "beacon id 9 is not in TL",
          "times repeat": "variable 'DR', row 5, column 1 (time): times not increasing",
          "not a MAT file": "not a readable MAT file", "truncated": "not a readable MAT file",
          "missing file": "missing file", "zero minutes": "--minutes must be a positive number"}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_malformed_input_exit_2_one_line_nothing_written(case, tmp_path, capsys):
    mat = tmp_path / "bad.mat"
    if case == "not a MAT file":
        mat.write_text("t,x,y\n1,2,3\n")
    elif case == "truncated":
        mat.write_bytes(b"MATLAB 5.0 MAT-file" + bytes(200))
    elif case != "missing file":
        scipy.io.savemat(mat, _broken(synthetic(), case))
    out = tmp_path / "out"
    extra = ["--minutes", "0"] if case == "zero minutes" else []
    assert main(["import-plaza", str(mat), "--out", str(out), *extra]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.count("\n") == 1 and cap.err.startswith("casm-graph: error: ")
    assert BROKEN[case] in cap.err
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())
