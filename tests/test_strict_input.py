"""Issue 23: bad data never wrecks a model, accepted logs never crash.

Every hostile input here ends in exit status 2 with one line naming the file (and row and column
where there is one): strict numbers and ids, magnitudes the units cannot have, logs the fit cannot
identify (a channel missing, too short, too few sightings, landmarks at one place), and broken
model files for diagnose, uncertainty and compare. model.json is strict JSON on the way out.
"""
import csv
import json
import math
import resource
import shutil
import subprocess
import sys

import numpy as np
import pytest

from casm_graph import cli
from casm_graph.io.log import LogError, load
from casm_graph.models.model import Model, paper_start
from casm_graph.pipeline.hidden_effect import model_error
from casm_graph.sim.aibo import SimConfig, simulate, write


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A 2-minute simulated Aibo bundle (action table, with pan and truth)."""
    d = tmp_path_factory.mktemp("strict") / "log"
    log, truth = simulate(SimConfig(minutes=2, seed=5))
    write(log, truth, d)
    return d


@pytest.fixture(scope="module")
def model_file(bundle, tmp_path_factory):
    """A valid model.json for the bundle (the paper's start with made-up velocities: no fit needed)."""
    log = load(bundle)
    m = paper_start(log)
    m = m.with_(velocities=np.tile([0.1, 0.0, 0.2], (len(m.action_ids), 1)))
    p = tmp_path_factory.mktemp("model") / "model.json"
    m.save(p)
    return p


def rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def put(path, table):
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(table)


def edited(src, dst, name, fn):
    """A copy of bundle ``src`` at ``dst`` with ``fn`` applied to the rows (header first) of ``name``."""
    shutil.copytree(src, dst)
    table = rows(dst / name)
    put(dst / name, fn(table) or table)
    return dst


def set_cell(row, col, value):
    def fn(table):
        table[row][table[0].index(col)] = value
    return fn


def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, err


def assert_one_line(code, err, *words):
    assert code == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, err)


def calibrate_rejects(capsys, d, tmp_path, *words):
    out = tmp_path / "run"
    code, err = run_cli(capsys, "calibrate", d, "--out", out, "--quiet")
    assert_one_line(code, err, *words)
    assert not out.exists()


# ----------------------------------------------------------------------------------- strict numbers

@pytest.mark.parametrize("cell", ["1_350", "\u0661\u0663", "\uff11.5", "0x10", "1e", ".", "+-1", "1.5.2", "1,5",
                                  "\u00a01", "1 000", "NaN", "-inf", "Infinity", "1e999"])
def test_number_not_plain_ascii_decimal(bundle, tmp_path, capsys, cell):
    d = edited(bundle, tmp_path / "log", "landmarks.csv", set_cell(2, "x", cell))
    with pytest.raises(LogError) as exc:
        load(d)
    msg = str(exc.value)
    assert "landmarks.csv, row 2, column 'x'" in msg and ("not a number" in msg or "not a finite number" in msg)
    calibrate_rejects(capsys, d, tmp_path, "landmarks.csv", "row 2", "column 'x'")


@pytest.mark.parametrize("cell,value", [("+1.5", 1.5), ("-.5", -0.5), ("2.", 2.0), ("1E-3", 1e-3), (" 3 ", 3.0),
                                        ("-0", 0.0), ("1e-400", 0.0)])
def test_plain_numbers_accepted(bundle, tmp_path, cell, value):
    d = edited(bundle, tmp_path / "log", "landmarks.csv", set_cell(2, "x", cell))
    assert load(d).landmark_xy[1, 0] == value


def test_ids_are_exact_integers(bundle, tmp_path):
    """9007199254740993 and 9007199254740992 are one float but two ids."""
    big = ["9007199254740992", "9007199254740993"]

    def landmarks(table):
        table[1][0], table[2][0] = big

    def observations(table):
        for r in table[1:]:
            if r[1] in ("0", "1"):
                r[1] = big[int(r[1])]

    d = edited(bundle, tmp_path / "log", "landmarks.csv", landmarks)
    table = rows(d / "observations.csv")
    observations(table)
    put(d / "observations.csv", table)
    log = load(d)
    assert log.landmark_ids[:2].tolist() == [9007199254740992, 9007199254740993]
    sel = log.obs_landmark == 9007199254740993
    assert sel.any() and np.all(log.landmark_index[sel] == 1)


@pytest.mark.parametrize("cell,words", [("9223372036854775808", "64 bits"), ("-99999999999999999999", "64 bits"),
                                        ("3.5", "not an integer"), ("2.5e0", "not an integer"), ("1e25", "64 bits"),
                                        ("\u0663", "not a number"), ("1_0", "not a number")])
def test_bad_ids(bundle, tmp_path, capsys, cell, words):
    d = edited(bundle, tmp_path / "log", "commands.csv", set_cell(4, "action", cell))
    calibrate_rejects(capsys, d, tmp_path, "commands.csv", "row 4", "column 'action'", words)


@pytest.mark.parametrize("name,row,col,value", [
    ("commands.csv", 5, "t", "1e300"),
    ("landmarks.csv", 1, "x", "1e300"),
    ("landmarks.csv", 3, "y", "-2e6"),
    ("observations.csv", 7, "reading", "1e300"),
    ("observations.csv", 7, "bearing", "7.0"),
    ("observations.csv", 2, "pan", "-100"),
    ("observations.csv", 2, "t", "1e300"),
])
def test_magnitudes_the_units_cannot_have(bundle, tmp_path, capsys, name, row, col, value):
    d = edited(bundle, tmp_path / "log", name, set_cell(row, col, value))
    calibrate_rejects(capsys, d, tmp_path, name, f"row {row}", f"column '{col}'", "out of range")


def test_times_scaled_to_nothing(bundle, tmp_path, capsys):
    def scale(table):
        j = table[0].index("t")
        for r in table[1:]:
            r[j] = repr(float(r[j]) * 1e-300)

    d = edited(bundle, tmp_path / "log", "commands.csv", scale)
    for name in ("observations.csv", "truth.csv"):
        table = rows(d / name)
        scale(table)
        put(d / name, table)
    calibrate_rejects(capsys, d, tmp_path, "commands.csv", "column 't'", "median step", "seconds")


@pytest.mark.parametrize("factor,words", [(5e7, "median step"), (1e-4, "median step")])
def test_times_scaled_within_the_bound(bundle, tmp_path, capsys, factor, words):
    """Times inside the magnitude bound but with implausible steps (a month, or microseconds, per command)."""
    def scale(table):
        j = table[0].index("t")
        for r in table[1:]:
            r[j] = repr(float(r[j]) * factor)

    d = edited(bundle, tmp_path / "log", "commands.csv", scale)
    for name in ("observations.csv", "truth.csv"):
        table = rows(d / name)
        scale(table)
        put(d / name, table)
    calibrate_rejects(capsys, d, tmp_path, "commands.csv", "column 't'", words)


def test_a_gap_of_more_than_a_day_splits_the_log(bundle, tmp_path, capsys):
    def gap(table):
        j = table[0].index("t")
        half = len(table) // 2
        for r in table[half:]:
            r[j] = repr(float(r[j]) + 1e9)

    d = edited(bundle, tmp_path / "log", "commands.csv", gap)
    calibrate_rejects(capsys, d, tmp_path, "commands.csv", "column 't'", "gap", "split the log")


def test_a_landmark_far_off_does_not_take_all_memory(bundle, tmp_path):
    """A landmark 900 km away (inside the position bound) once made the start's grid smoother ask for 22 GB:
    under a 3 GB address-space limit calibrate now ends in a model or one line."""
    def far(table):
        table[1][table[0].index("x")] = "9e5"

    d = edited(bundle, tmp_path / "log", "landmarks.csv", far)
    limit = (lambda: resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)))
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "calibrate", str(d), "--out", str(tmp_path / "run"),
                        "--quiet"], capture_output=True, text=True, preexec_fn=limit, timeout=600)
    assert r.returncode in (0, 2), r.stderr[-2000:]
    assert "Traceback" not in r.stderr and "MemoryError" not in r.stderr


# ----------------------------------------------------------------------------- accepted, then a crash

def short(n):
    """Keep the first ``n`` command steps (and the sightings within them); truth.csv removed."""
    def fn(d):
        cm = rows(d / "commands.csv")
        put(d / "commands.csv", cm[:n + 1])
        t_end = float(cm[n][0])
        ob = rows(d / "observations.csv")
        kept = [r for r in ob[1:] if float(r[0]) <= t_end]
        if not kept:                         # keep the file non-empty: sightings moved to the first step
            kept = [[cm[1][0], *r[1:]] for r in ob[1:4]]
        put(d / "observations.csv", [ob[0]] + kept)
        (d / "truth.csv").unlink()
    return fn


def many_actions(fn):
    """``fn``, then a new action every 5 steps: more unknowns than a short log's sightings."""
    def g(d):
        fn(d)
        table = rows(d / "commands.csv")
        for i, r in enumerate(table[1:]):
            r[1] = str(100 + i // 5)
        put(d / "commands.csv", table)
    return g


def few_bearings(fn, keep):
    """``fn``, then the bearings of all but the first ``keep`` sightings left empty."""
    def g(d):
        fn(d)
        table = rows(d / "observations.csv")
        for r in table[1 + keep:]:
            r[3] = ""
        put(d / "observations.csv", table)
    return g


def empty_column(col):
    def fn(d):
        table = rows(d / "observations.csv")
        j = table[0].index(col)
        for r in table[1:]:
            r[j] = ""
        put(d / "observations.csv", table)
    return fn


def bearings_only_without_actions_csv(d):
    empty_column("reading")(d)
    (d / "actions.csv").unlink()


def constant(col, value):
    def fn(d):
        table = rows(d / "observations.csv")
        j = table[0].index(col)
        for r in table[1:]:
            if r[j]:
                r[j] = value
        put(d / "observations.csv", table)
    return fn


def one_step_action(d):
    table = rows(d / "commands.csv")
    table[10][1] = "999"
    put(d / "commands.csv", table)


def few_sightings(d):
    put(d / "observations.csv", rows(d / "observations.csv")[:6])


def coincident(d):
    table = rows(d / "landmarks.csv")
    for r in table[1:]:
        r[1], r[2] = "1.0", "1.0"
    put(d / "landmarks.csv", table)


CRASHES = [
    ("three_commands", short(3), ["commands.csv", "only 3 command step", "too short"]),
    ("one_step_action", one_step_action, ["commands.csv", "row 10", "column 'action'", "action 999",
                                          "only 1 step", "at least 15 command steps"]),
    ("bearings_only_no_actions_csv", bearings_only_without_actions_csv,
     ["observations.csv", "column 'reading'", "a bearing-only log", "needs actions.csv"]),
    ("few_sightings", few_sightings, ["observations.csv", "only 5 sighting", "at least 10"]),
    ("coincident_landmarks", coincident, ["landmarks.csv", "columns 'x','y'", "coincident",
                                          "sensor polynomial cannot be identified"]),
    ("constant_reading", constant("reading", "10"), ["observations.csv", "column 'reading'", "1 distinct value",
                                                     "constant reading"]),
    ("constant_bearing", constant("bearing", "0.1"), ["observations.csv", "column 'bearing'", "constant bearing"]),
    ("short_log", few_bearings(many_actions(short(40)), 12), ["observations.csv", "unknowns", "8 action(s)",
                                                               "too short for this model"]),
]


@pytest.mark.parametrize("case,fn,words", CRASHES, ids=[c[0] for c in CRASHES])
def test_accepted_logs_the_fit_cannot_take(bundle, tmp_path, capsys, case, fn, words):
    d = tmp_path / "log"
    shutil.copytree(bundle, d)
    fn(d)
    load(d)                                  # well formed: the loader accepts it
    out = tmp_path / "run"
    code, err = run_cli(capsys, "calibrate", d, "--out", out, "--quiet", "--sensor-degree", 6)
    assert_one_line(code, err, *words)       # refused before any computation, not a crash or a NaN model
    assert not out.exists()


def test_short_runs_of_an_action_that_also_runs_long_are_calibrated(bundle, tmp_path, capsys):
    """A 3-step run (and a 1-step one) of actions that run for seconds elsewhere: the start takes them in stride."""
    d = tmp_path / "log"
    shutil.copytree(bundle, d)
    table = rows(d / "commands.csv")
    table[200][1] = table[201][1] = table[202][1] = table[900][1]
    table[600][1] = table[1200][1]
    put(d / "commands.csv", table)
    out = tmp_path / "run"
    code, err = run_cli(capsys, "calibrate", d, "--out", out, "--quiet")
    assert code == 0, err
    data = json.loads((out / "model.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in model.json"))
    truth = json.loads((bundle / "truth_model.json").read_text())
    err = model_error(Model.load(out / "model.json"), truth)
    assert data["fit"]["converged"] and err["vx"] < 0.05 and err["vy"] < 0.05, err


def test_a_short_log_that_is_enough_gives_a_finite_model(bundle, tmp_path, capsys):
    d = tmp_path / "log"
    shutil.copytree(bundle, d)
    short(300)(d)
    out = tmp_path / "run"
    code, err = run_cli(capsys, "calibrate", d, "--out", out, "--quiet")
    if code == 2:
        assert_one_line(code, err)
        return
    assert code == 0, err
    data = json.loads((out / "model.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in model.json"))
    m = data["sensor_model"]
    assert math.isfinite(data["fit"]["log_likelihood"]) and m["reading_sigma"] > 0 and m["bearing_sigma"] > 0


def test_truth_at_other_times_is_interpolated_or_left_out(bundle, tmp_path):
    """truth.csv is information only: a log cut short keeps its truth at the pose times; never an error."""
    full = load(bundle)
    d = tmp_path / "log"
    shutil.copytree(bundle, d)
    short(100)(d)
    shutil.copy(bundle / "truth.csv", d / "truth.csv")
    log = load(d)
    assert log.truth.shape == (101, 4)
    np.testing.assert_allclose(log.truth, full.truth[:101], atol=1e-8)
    tr = rows(d / "truth.csv")
    put(d / "truth.csv", tr[:50])            # covers only part of the log
    assert load(d).truth is None


# ------------------------------------------------------------------------------------ bad model files

def _good(model_file):
    return json.loads(model_file.read_text())


def _mutate(fn):
    def make(model_file):
        d = _good(model_file)
        fn(d)
        return json.dumps(d)
    return make


BAD_MODELS = [
    ("json_list", lambda m: "[1, 2, 3]", "top level must be a JSON object"),
    ("binary", lambda m: bytes(range(256)) * 4, "not a UTF-8 text file"),
    ("deep_nesting", lambda m: "[" * 100000 + "]" * 100000, "nested too deeply"),
    ("deep_in_fit", _mutate(lambda d: d["fit"].__setitem__("x", json.loads("[" * 200 + "]" * 200))), "nested"),
    ("zero_sigma", _mutate(lambda d: d["sensor_model"].__setitem__("reading_sigma", 0)), "must be positive"),
    ("negative_sigma", _mutate(lambda d: d["sensor_model"].__setitem__("bearing_sigma", -0.5)), "must be positive"),
    ("nan_velocity", lambda m: m.read_text().replace("[\n        0.1,", "[\n        NaN,", 1), "NaN"),
    ("null_velocity", _mutate(lambda d: d["action_model"]["velocities"].__setitem__(
        next(iter(d["action_model"]["velocities"])), [None, 0, 0])), "expected a number"),
    ("huge_number", lambda m: m.read_text().replace('"reading_sigma": ', '"reading_sigma": 1e400, "x": ', 1),
     "finite"),
    ("missing_sensor_model", _mutate(lambda d: d.pop("sensor_model")), "sensor_model is missing"),
    ("missing_velocities", _mutate(lambda d: d["action_model"].pop("velocities")), "velocities is missing"),
    ("missing_schema", _mutate(lambda d: d.pop("schema")), "schema"),
    ("string_sigma", _mutate(lambda d: d["sensor_model"].__setitem__("reading_sigma", "1")), "must be a number"),
    ("zero_motion_noise", _mutate(lambda d: d.__setitem__("motion_noise", [0, 0, 0])), "must be positive"),
    ("unicode_action_id", _mutate(lambda d: d["action_model"]["velocities"].__setitem__("\u0663", [0, 0, 0])),
     "not an integer action id"),
    ("effect_param_null", _mutate(lambda d: d["effects"].__setitem__("actuator_lag", {"tau": None})),
     "effects.actuator_lag.tau"),
    ("friction_flat_extent", _mutate(lambda d: d["effects"].__setitem__("surface_friction", {
        "slow_0_0": 0.1, "slow_1_0": 0, "slow_0_1": 0, "slow_1_1": 0, "order": 2, "grid": [2, 2],
        "extent": [0, 0, 0, 1]})), "effects.surface_friction.extent"),
    ("friction_unknown_order", _mutate(lambda d: d["effects"].__setitem__("surface_friction", {
        "slow_0_0": 0.1, "order": 7, "grid": [7, 7], "extent": [0, 0, 1, 1]})), "effects.surface_friction.order"),
    ("empty_file", lambda m: "", "not valid JSON"),
    ("denormal_sigma", _mutate(lambda d: d["sensor_model"].__setitem__("reading_sigma", 1e-320)), "units allow"),
    ("huge_sigma", _mutate(lambda d: d["sensor_model"].__setitem__("reading_sigma", 1e300)), "units allow"),
    ("huge_coefficient", _mutate(lambda d: d["sensor_model"].__setitem__("reading_poly", [1e308, 1e308, 0, 0])),
     "units allow"),
]


@pytest.mark.parametrize("case,make,words", BAD_MODELS, ids=[b[0] for b in BAD_MODELS])
def test_bad_model_files(bundle, model_file, tmp_path, capsys, case, make, words):
    content = make(model_file)
    bad = tmp_path / "run" / "model.json"
    bad.parent.mkdir()
    (bad.write_bytes if isinstance(content, bytes) else bad.write_text)(content)
    with pytest.raises(LogError):
        Model.load(bad)
    measured = tmp_path / "measured"
    measured.mkdir()
    (measured / "sensor.csv").write_text("distance,reading\n1.0,10\n2.0,5\n")
    for argv in (["diagnose", bundle, "--model", bad, "--out", tmp_path / "diag", "--quiet"],
                 ["uncertainty", bundle, "--model", bad, "--out", tmp_path / "unc", "--quiet"],
                 ["compare", bad, "--measured", measured, "--out", tmp_path / "cmp"]):
        code, err = run_cli(capsys, *argv)
        assert_one_line(code, err, "model.json: ", words)
        assert not argv[argv.index("--out") + 1].exists()


def test_the_valid_model_file_loads(model_file):
    m = Model.load(model_file)
    assert len(m.action_ids) and np.all(m.velocities[:, 0] == 0.1)


# ------------------------------------------------------------------------------------ strict JSON out

def test_model_json_is_strict(model_file, tmp_path):
    m = Model.load(model_file)
    m = m.with_(velocity_std=np.full_like(m.velocities, np.nan), reading_poly_std=np.array([np.nan, 1, 2, np.inf]),
                fit={"log_likelihood": float("nan"), "seconds": np.float64(np.inf)})
    p = tmp_path / "model.json"
    m.save(p)
    text = p.read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text, parse_constant=lambda c: pytest.fail(c))
    assert data["fit"]["log_likelihood"] is None and data["sensor_model"]["reading_poly_std"][3] is None
    back = Model.load(p)                     # nulls read back as unknown (NaN) where a std may be unknown
    assert np.isnan(back.velocity_std).all() and np.isnan(back.reading_poly_std[0])


def test_model_save_refuses_non_finite_json(model_file, tmp_path, monkeypatch):
    """The dump itself is strict: a NaN that slipped past to_json fails loudly, it is never written."""
    m = Model.load(model_file)
    monkeypatch.setattr(Model, "to_json", lambda self: {"schema": "x", "bad": float("nan")})
    with pytest.raises(ValueError):
        m.save(tmp_path / "model.json")


# ------------------------------------------------------------------------------------ compare's CSVs

@pytest.mark.parametrize("text,words", [
    ("distance,reading\n1_0,5\n", ["sensor.csv", "row 1", "column 'distance'", "not a number"]),
    ("distance,reading\n1e300,5\n", ["sensor.csv", "row 1", "column 'distance'", "out of range"]),
    ("distance,reading,std\n1,5,-1\n", ["sensor.csv", "row 1", "column 'std'", "negative"]),
    ("distance,reading\n-1,5\n", ["sensor.csv", "row 1", "column 'distance'", "negative"]),
])
def test_compare_measured_tables(model_file, tmp_path, capsys, text, words):
    measured = tmp_path / "measured"
    measured.mkdir()
    (measured / "sensor.csv").write_text(text)
    code, err = run_cli(capsys, "compare", model_file, "--measured", measured, "--out", tmp_path / "cmp")
    assert_one_line(code, err, *words)
