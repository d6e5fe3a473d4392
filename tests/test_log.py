"""Log bundles: round trip, and every bad input of INTERFACE section 1 rejected with file, row, column."""
import json
import shutil

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.cli import main
from casm_graph.io.log import LogError, held_steps, load, sighting_steps
from casm_graph.io.log import write as write_log


def test_round_trip(short_bundle):
    d, log, _ = short_bundle
    back = load(d)
    np.testing.assert_array_equal(back.action, log.action)
    np.testing.assert_allclose(back.t, log.t)
    np.testing.assert_allclose(back.obs_reading, log.obs_reading, atol=1e-8)
    np.testing.assert_allclose(back.obs_bearing, log.obs_bearing, atol=1e-8)
    np.testing.assert_allclose(back.truth, log.truth, atol=1e-8)
    assert back.steps == log.steps and len(back.obs_t) == len(log.obs_t)


def _edit(src, dst, name, fn):
    shutil.copytree(src, dst)
    p = dst / name
    lines = p.read_text().splitlines()
    p.write_text("\n".join(fn(lines)) + "\n")
    return dst


def _set_cell(row, col, value):
    def fn(lines):
        header = lines[0].split(",")
        cells = lines[row].split(",")
        cells[header.index(col)] = value
        lines[row] = ",".join(cells)
        return lines
    return fn


BAD = [
    ("missing_file", "landmarks.csv", None, ["landmarks.csv", "missing file"]),
    ("missing_column", "observations.csv", lambda L: [L[0].replace("bearing", "bear")] + L[1:],
     ["observations.csv", "missing column 'bearing'"]),
    ("non_numeric", "observations.csv", _set_cell(3, "reading", "abc"),
     ["observations.csv", "row 3", "column 'reading'", "not a number"]),
    ("nan", "commands.csv", _set_cell(5, "t", "nan"), ["commands.csv", "row 5", "column 't'", "finite"]),
    ("inf", "landmarks.csv", _set_cell(2, "x", "inf"), ["landmarks.csv", "row 2", "column 'x'", "finite"]),
    ("times_not_increasing", "commands.csv", lambda L: L[:10] + [L[12], L[11]] + L[13:],
     ["commands.csv", "row 11", "column 't'", "not increasing"]),
    ("unknown_landmark", "observations.csv", _set_cell(4, "landmark", "17"),
     ["observations.csv", "row 4", "column 'landmark'", "unknown landmark id 17"]),
    ("empty_log", "commands.csv", lambda L: L[:1], ["commands.csv", "no data rows"]),
    ("empty_required_cell", "commands.csv", _set_cell(2, "action", ""),
     ["commands.csv", "row 2", "column 'action'", "empty"]),
    ("duplicate_landmark", "landmarks.csv", _set_cell(2, "landmark", "0"),
     ["landmarks.csv", "row 2", "column 'landmark'", "twice"]),
]


@pytest.mark.parametrize("case,name,edit,words", BAD, ids=[b[0] for b in BAD])
def test_bad_input_is_one_clear_message(short_bundle, tmp_path, capsys, case, name, edit, words):
    src = short_bundle[0]
    if edit is None:
        d = tmp_path / "log"
        shutil.copytree(src, d)
        (d / name).unlink()
    else:
        d = _edit(src, tmp_path / "log", name, edit)
    with pytest.raises(LogError) as exc:
        load(d)
    for w in words:
        assert w in str(exc.value)
    out = tmp_path / "run"
    assert main(["calibrate", str(d), "--out", str(out)]) == 2      # the command's own entry, in process
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.count("\n") == 1 and all(w in err for w in words)
    assert not out.exists()


def _changes_only(src, dst):
    """A copy of bundle ``src`` whose commands.csv keeps only the rows where the command changes."""
    shutil.copytree(src, dst)
    lines = (dst / "commands.csv").read_text().splitlines()
    vals = [r.split(",")[1:] for r in lines[1:]]
    keep = [r for i, r in enumerate(lines[1:]) if i == 0 or vals[i] != vals[i - 1]]
    (dst / "commands.csv").write_text("\n".join([lines[0]] + keep) + "\n")
    return dst, len(keep)


def test_commands_written_only_when_they_change_are_the_same_log(short_bundle, tmp_path):
    """A log that writes a command row only at a change (a row every few seconds, sightings at 30 Hz) holds each row
    over the sightings' frame: the same steps, actions and poses of the sightings as one row per step, the same
    calibration, and errors that name the file's rows."""
    d, log, _ = short_bundle
    changed, rows = _changes_only(d, tmp_path / "changes")
    back = load(changed)
    n = back.steps
    assert rows < log.steps / 20 and back.command_row is not None and n <= log.steps
    assert np.all(back.obs_t <= back.pose_times[-1]) and n > log.steps - 30    # held until the last sighting
    np.testing.assert_allclose(back.t, log.t[:n], atol=1e-9)
    np.testing.assert_array_equal(back.action, log.action[:n])
    np.testing.assert_array_equal(back.obs_step, log.obs_step)
    np.testing.assert_allclose(back.truth, log.truth[:n + 1], atol=1e-8)
    assert back.file_row(0) == 1 and back.file_row(n - 1) == rows
    full, held = cg.calibrate(load(d), seed=0), cg.calibrate(back, seed=0)
    assert held.model.fit["log_likelihood"] == pytest.approx(full.model.fit["log_likelihood"], abs=1.0)
    np.testing.assert_allclose(held.model.velocities, full.model.velocities, atol=2e-3)
    assert held.model_json["fit"]["held_commands"]["rows"] == rows and "held_commands" not in full.model_json["fit"]
    assert f"the {rows} rows of commands.csv held" in held.summary()
    frames = np.arange(0.0, 60.0, 1 / 30)            # three tags a frame, stamped 1 ms apart: one frame, not three
    tags = np.sort(np.concatenate([frames, frames + 0.001, frames + 0.002]))
    assert held_steps(frames, tags) is None
    rows, times = held_steps(frames[::150], tags)    # a row every 5 s: held over the 30-Hz frames
    assert np.median(np.diff(times)) == pytest.approx(1 / 30, rel=0.1) and rows[-1] == 11


def test_continuous_commands_written_only_when_they_change_calibrate_alike(tmp_path):
    """The same for continuous commands: SCASM's 1-D walk (a speed held for seconds at a time) written at changes
    only gives SCASM-graph's calibration of the full log."""
    log, _ = cg.simulate("scasm-1d", minutes=2, seed=1)
    write_log(log, tmp_path / "full")
    changed, rows = _changes_only(tmp_path / "full", tmp_path / "changes")
    back = load(changed)
    assert back.command_row is not None and rows < log.steps / 20
    full, held = (cg.calibrate(load(p), method="scasm-graph", seed=0) for p in (tmp_path / "full", changed))
    assert held.model["fit"]["log_likelihood"] == pytest.approx(full.model["fit"]["log_likelihood"], abs=0.1)
    for part in ("action_model", "sensor_model"):
        np.testing.assert_allclose(held.model[part]["coefficients"], full.model[part]["coefficients"], rtol=1e-5)


def test_sightings_off_the_commands_grid_get_poses_of_their_own(tmp_path):
    """A camera on its own clock (frames 40 ms after each 10-Hz command row here): each sighting time starts a step
    under the row that holds there, so every sighting is seen from the pose of its own time; each row still moves
    the robot as far, truth is interpolated at the new poses, and a few ms of jitter (MRCLAM's) changes nothing."""
    log, _ = cg.simulate("floor", minutes=1, seed=0)
    moved = cg.Log(**{**log.__dict__, "obs_t": log.obs_t + 0.04})
    write_log(moved, tmp_path / "off")
    back = load(tmp_path / "off")
    first = np.flatnonzero(np.diff(np.append(-1, back.command_row)))
    assert len(first) == log.steps and back.steps == log.steps + len(np.unique(log.obs_t)) - 1
    np.testing.assert_allclose(back.t[first], log.t, atol=1e-9)
    np.testing.assert_allclose(back.controls, log.controls[back.command_row], atol=1e-8)
    inside = back.obs_t < log.pose_times[-1]          # one frame after the last command's step: the final pose
    assert np.abs(back.obs_t - back.pose_times[back.obs_step])[inside].max() < 1e-9
    assert len(np.unique(back.obs_t[~inside])) == 1
    rows = np.zeros((log.steps, 2))
    np.add.at(rows, back.command_row, back.controls * back.dt[:, None])
    np.testing.assert_allclose(rows[:-1], (log.controls * log.dt[:, None])[:-1], atol=1e-8)
    np.testing.assert_allclose(back.truth[first, 1:3], log.truth[:-1, 1:3], atol=1e-6)
    assert f"the {log.steps} rows of commands.csv held" in cg.calibrate(back, seed=0).summary()
    jitter = log.obs_t + np.random.default_rng(0).uniform(-0.008, 0.008, len(log.obs_t))
    assert sighting_steps(log.t, np.sort(jitter)) is None


def test_observations_written_landmark_by_landmark_are_taken_in_time_order(short_bundle, tmp_path, capsys):
    """A generator that writes each landmark's sightings in turn: the rows are sorted by time (stably), with one
    warning naming the first row out of order, and the log calibrates as the time-ordered one."""
    d, log, _ = short_bundle
    shutil.copytree(d, tmp_path / "by_landmark")
    lines = (d / "observations.csv").read_text().splitlines()
    rows = sorted(lines[1:], key=lambda r: int(r.split(",")[1]))           # stable: time order within a landmark
    (tmp_path / "by_landmark" / "observations.csv").write_text("\n".join([lines[0]] + rows) + "\n")
    with pytest.warns(RuntimeWarning, match=r"observations.csv, row \d+, column 't'.*taken in time order"):
        back = load(tmp_path / "by_landmark")
    order = np.lexsort((log.obs_landmark, log.obs_t))                        # within a time, landmark by landmark
    np.testing.assert_allclose(back.obs_t, log.obs_t[order], atol=1e-9)
    np.testing.assert_array_equal(back.obs_landmark, log.obs_landmark[order])
    np.testing.assert_allclose(back.obs_reading, log.obs_reading[order], atol=1e-8)
    assert main(["calibrate", str(tmp_path / "by_landmark"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert capsys.readouterr().err.count("taken in time order") == 1
    assert main(["calibrate", str(d), "--out", str(tmp_path / "run0"), "--quiet"]) == 0
    fits = [json.loads((tmp_path / r / "model.json").read_text())["fit"] for r in ("run", "run0")]
    assert fits[0]["log_likelihood"] == pytest.approx(fits[1]["log_likelihood"], rel=1e-6)


def test_a_written_nan_in_an_optional_column_is_not_measured(short_bundle, tmp_path):
    """numpy's ``savetxt`` writes ``nan`` where a component was not measured: in reading, bearing and pan that
    reads as the empty cell does (in a required column it stays an error, above)."""
    d, _, _ = short_bundle
    lines = (d / "observations.csv").read_text().splitlines()
    empty, nan = [lines[0]], [lines[0]]
    for k, row in enumerate(lines[1:]):
        cells = row.split(",")
        cells[2 + k % 2] = ""                            # every row keeps one of reading and bearing
        empty.append(",".join(cells))
        cells[2 + k % 2] = ("nan", "NaN")[k % 2]
        nan.append(",".join(cells))
    for name, rows in (("empty", empty), ("nan", nan)):
        shutil.copytree(d, tmp_path / name)
        (tmp_path / name / "observations.csv").write_text("\n".join(rows) + "\n")
    a, b = load(tmp_path / "empty"), load(tmp_path / "nan")
    assert np.isnan(a.obs_reading).sum() == len(a.obs_t) - len(a.obs_t) // 2
    np.testing.assert_array_equal(a.obs_reading, b.obs_reading)
    np.testing.assert_array_equal(a.obs_bearing, b.obs_bearing)


def test_a_bundle_written_by_numpy_savetxt_reads_alike(short_bundle, tmp_path):
    """Every file written as ``np.savetxt(..., delimiter=",", header=...)`` does by default: the header after
    "# ", each number as ``%.18e`` (ids too: 3.000000000000000000e+00) and a component not measured as ``nan``."""
    d, _, _ = short_bundle
    out = tmp_path / "savetxt"
    out.mkdir()
    for f in d.glob("*.csv"):
        lines = f.read_text().splitlines()
        rows = [[float(c) if c != "" else np.nan for c in r.split(",")] for r in lines[1:]]
        np.savetxt(out / f.name, np.array(rows), delimiter=",", header=lines[0])      # "# t,landmark,..."
    a, b = load(d), load(out)
    assert "e+00" in (out / "observations.csv").read_text().splitlines()[1].split(",")[1]
    for name in ("t", "action", "obs_t", "obs_landmark", "obs_reading", "obs_bearing", "landmark_ids",
                 "landmark_xy", "truth"):
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=1e-12, err_msg=name)


def test_sightings_outside_the_commands_are_set_aside_with_a_warning(short_bundle, tmp_path, capsys):
    """A camera that starts before the first command or runs on after the last: those sightings are set aside with
    one warning (count, first row), the rest calibrate; a log with no sighting inside the span is still refused."""
    d, log, _ = short_bundle
    shutil.copytree(d, tmp_path / "cut")
    lines = (d / "commands.csv").read_text().splitlines()
    (tmp_path / "cut" / "commands.csv").write_text("\n".join([lines[0]] + lines[31:-90]) + "\n")
    with pytest.warns(RuntimeWarning, match=r"observations.csv: [\d,]+ sighting\(s\) outside the commands' span.*"
                                            r"the first at row 1 .*set aside"):
        back = load(tmp_path / "cut")
    t0, t1 = log.t[30], log.t[-91]
    step = float(np.median(np.diff(log.t)))
    inside = (log.obs_t >= t0 - step / 2) & (log.obs_t <= t1 + 1.5 * step)
    assert 0 < inside.sum() < len(log.obs_t) and len(back.obs_t) == inside.sum()
    np.testing.assert_allclose(back.obs_t, log.obs_t[inside], atol=1e-9)
    assert main(["calibrate", str(tmp_path / "cut"), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert capsys.readouterr().err.count("set aside") == 1
    (tmp_path / "cut" / "commands.csv").write_text(f"{lines[0]}\n500,1\n500.1,1\n500.2,1\n")
    with pytest.raises(LogError, match="every sighting lies outside the commands' span"):
        load(tmp_path / "cut")
