"""Properties of the log loader on generated bundles (issue 23).

Whatever the cells hold, ``load`` returns a Log or raises LogError, never anything else; the numbers
it accepts are exactly those a strict ASCII decimal parser accepts, with the values that parser
gives, and ids are exact integers.
"""
import csv
import io
import json
import math
import re
import tempfile
from contextlib import redirect_stderr
from decimal import Decimal
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from casm_graph.cli import main
from casm_graph.io.log import MAX_POSITION, Log, LogError, load

from .conftest import FULL

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

WEIRD = ["1_350", "\u0661\u0663", "\uff11", "\u00b2", "0x10", "0b1", "1e", "e1", ".", "-", "+", "+-1", "1.5.2",
         "1,5", "nan", "NaN", "-inf", "Infinity", "inf", "1e999", "-1e400", "1e-400", "1e300", "-0", "+.5", "5.",
         ".5e-3", "1E+2", " 7 ", "\t8", "\u00a09", "9\u2009", "1 000", "", " ", "٣", "00012", "1e05", "True",
         "9007199254740993", "9223372036854775807", "9223372036854775808", "-9223372036854775808", "3.0", "3.00",
         "3.01", "1e3", "\x00", "\n", '"', "1\n2"]

cells = st.one_of(
    st.sampled_from(WEIRD),
    st.integers(-10 ** 20, 10 ** 20).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e7, 1e7).map(lambda x: f"{x:.3e}"),
    st.text(alphabet="0123456789+-.eE _", max_size=8),
    st.text(max_size=5),
)


def strict_number(cell: str):
    """Reference parser: optional sign, ASCII digits with at most one point (a digit on some side),
    optional exponent of ASCII digits; surrounding spaces and tabs allowed. None when not a number."""
    s = cell.strip(" \t\r\n")
    i, n = 0, len(s)
    if i < n and s[i] in "+-":
        i += 1
    digits = 0
    while i < n and s[i] in "0123456789":
        i, digits = i + 1, digits + 1
    if i < n and s[i] == ".":
        i += 1
        while i < n and s[i] in "0123456789":
            i, digits = i + 1, digits + 1
    if digits == 0:
        return None
    if i < n and s[i] in "eE":
        i += 1
        if i < n and s[i] in "+-":
            i += 1
        exp = 0
        while i < n and s[i] in "0123456789":
            i, exp = i + 1, exp + 1
        if exp == 0:
            return None
    if i != n:
        return None
    return float(s)


def strict_id(cell: str):
    """Reference integer id: optional sign, ASCII digits, optionally '.' and digits and an exponent (numpy's
    savetxt writes 3.000000000000000000e+00), of an exactly integral value within int64."""
    s = cell.strip(" \t\r\n")
    if not re.fullmatch(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", s, re.ASCII):
        return None
    d = Decimal(s)
    if d.adjusted() > 19 or d != d.to_integral_value():
        return None
    v = int(d)
    return v if abs(v) <= 2 ** 63 - 1 else None


def not_measured(cell: str) -> bool:
    """An optional column's cell that says the component was not measured: empty, or NaN written out."""
    return cell.strip(" \t\r\n").lstrip("+-").lower() in ("", "nan")


def write_csv(path: Path, rows):
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f).writerows(rows)


def bundle(d: Path, landmark_x=None, actions=None):
    """A small valid bundle, with the landmark x cells or the action cells replaced when given."""
    xs = landmark_x or ["0", "1", "2"]
    write_csv(d / "landmarks.csv", [["landmark", "x", "y"]] + [[str(i), x, str(i % 2)] for i, x in enumerate(xs)])
    acts = actions or ["1"] * 6
    write_csv(d / "commands.csv", [["t", "action"]] + [[f"{0.1 * i:.1f}", a] for i, a in enumerate(acts)])
    write_csv(d / "observations.csv", [["t", "landmark", "reading", "bearing"],
                                       ["0.0", "0", "10", "0.5"], ["0.2", "1", "12", ""], ["0.3", "2", "", "-1"]])


@SETTINGS
@given(st.lists(cells, min_size=1, max_size=4))
def test_landmark_numbers_are_exactly_the_strict_ascii_decimals(xs):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        xs = (xs + ["0", "1", "2"])[:max(3, len(xs))]
        bundle(d, landmark_x=xs)
        ref = [strict_number(x) for x in xs]
        ok = all(v is not None and math.isfinite(v) and abs(v) <= MAX_POSITION for v in ref)
        try:
            log = load(d)
        except LogError as exc:
            assert not ok, (xs, str(exc))
            assert "\n" not in str(exc)
            return
        assert ok, xs
        assert log.landmark_xy[:, 0].tolist() == ref


@SETTINGS
@given(st.lists(cells, min_size=1, max_size=6))
def test_action_ids_are_exact_integers(acts):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        acts = (acts + ["1"] * 6)[:max(6, len(acts))]
        bundle(d, actions=acts)
        ref = [strict_id(a) for a in acts]
        try:
            log = load(d)
        except LogError as exc:
            assert any(v is None for v in ref), (acts, str(exc))
            assert "\n" not in str(exc)
            return
        assert all(v is not None for v in ref), acts
        assert log.action.dtype == np.int64 and log.action.tolist() == ref


TABLES = {"landmarks.csv": ["landmark", "x", "y"],
          "commands.csv": ["t", "action"],
          "observations.csv": ["t", "landmark", "reading", "bearing", "pan"]}


@st.composite
def bundles(draw):
    """Every cell drawn from numbers, near-numbers and junk; sometimes ragged rows or a missing header cell."""
    out = {}
    for name, header in TABLES.items():
        n = draw(st.integers(0, 5))
        rows = [[draw(cells) for _ in header] for _ in range(n)]
        if rows and draw(st.booleans()):
            rows[draw(st.integers(0, n - 1))].pop()
        out[name] = [header] + rows
    return out


@SETTINGS
@given(bundles())
def test_load_returns_a_log_or_raises_log_error(tables):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for name, rows in tables.items():
            write_csv(d / name, rows)
        try:
            log = load(d)
        except LogError as exc:
            assert "\n" not in str(exc)
            return
        assert isinstance(log, Log)
        assert np.all(np.isfinite(log.t)) and np.all(np.isfinite(log.landmark_xy))


@SETTINGS
@given(st.lists(st.sampled_from(WEIRD) | cells, min_size=1, max_size=30))
def test_valid_bundle_with_one_column_of_junk_readings(readings):
    """Mostly valid bundles: the loader still only returns a Log or raises LogError, and keeps the values."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        bundle(d)
        obs = [["t", "landmark", "reading", "bearing"]] + [["0.1", str(i % 3), r, "0.1"]
                                                           for i, r in enumerate(readings)]
        write_csv(d / "observations.csv", obs)
        ref = [None if not_measured(r) else strict_number(r) for r in readings]
        try:
            log = load(d)
        except LogError:
            return
        for r, v, got in zip(readings, ref, log.obs_reading):
            if not_measured(r):
                assert np.isnan(got)
            else:
                assert v is not None and got == v, (r, got)


# ----------------------------------------------------------------------------------------------- the CLI
SMALL = {}


def small_bundle() -> tuple:
    """A 40-second simulated log (built once), as the columns the CLI test perturbs."""
    if not SMALL:
        from casm_graph.sim.protocols import simulate
        log, _ = simulate("aibo", minutes=40 / 60, seed=3)
        SMALL["log"] = log
    return SMALL["log"]


def write_bundle(d: Path, log, reading, bearing, landmark, t_scale: float) -> None:
    d.mkdir()
    with open(d / "landmarks.csv", "w") as f:
        f.write("landmark,x,y\n" + "".join(f"{i},{x!r},{y!r}\n" for i, (x, y) in zip(log.landmark_ids,
                                                                                       log.landmark_xy.tolist())))
    with open(d / "commands.csv", "w") as f:
        f.write("t,action\n" + "".join(f"{t * t_scale!r},{a}\n" for t, a in zip(log.t.tolist(), log.action)))
    with open(d / "observations.csv", "w") as f:
        f.write("t,landmark,reading,bearing\n" + "".join(
            f"{t * t_scale!r},{k},{r},{b}\n" for t, k, r, b in zip(log.obs_t.tolist(), landmark, reading, bearing)))


def test_the_perturbed_bundles_start_from_a_valid_one(tmp_path):
    """Unperturbed, the property below's bundle loads as the log it was written from (else every example would be
    refused for the writer's sake and the property would say nothing)."""
    log = small_bundle()
    write_bundle(tmp_path / "log", log, [repr(float(x)) for x in log.obs_reading],
                 [repr(float(x)) for x in log.obs_bearing], [str(int(k)) for k in log.obs_landmark], 1.0)
    back = load(tmp_path / "log")
    assert np.array_equal(back.obs_reading, log.obs_reading) and np.array_equal(back.landmark_xy, log.landmark_xy)


@settings(max_examples=12 if FULL else 8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_calibrate_gives_a_sane_model_or_one_line(data):
    """Perturbed small logs through ``casm-graph calibrate``: exit 0 with a finite model.json and complete output,
    or exit 2 with one line and nothing written; never a traceback, never NaN."""
    log = small_bundle()
    n = len(log.obs_t)
    reading = [repr(float(x)) for x in log.obs_reading]
    bearing = [repr(float(x)) for x in log.obs_bearing]
    landmark = [str(int(k)) for k in log.obs_landmark]
    for _ in range(data.draw(st.integers(0, 4), label="cells changed")):
        i = data.draw(st.integers(0, n - 1), label="row")
        col = data.draw(st.sampled_from(["reading", "bearing", "landmark"]), label="column")
        cell = data.draw(st.one_of(st.sampled_from(WEIRD), st.floats(-1e12, 1e12).map(repr)), label="cell")
        {"reading": reading, "bearing": bearing, "landmark": landmark}[col][i] = cell.replace("\n", " ").replace('"', "")
    if data.draw(st.booleans(), label="wipe a channel"):
        col = data.draw(st.sampled_from([reading, bearing]), label="channel")
        col[:] = [""] * n
    t_scale = data.draw(st.sampled_from([1.0, 1.0, 1e-9, 1e6]), label="time scale")
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "log"
        write_bundle(d, log, reading, bearing, landmark, t_scale)
        out = Path(tmp) / "run"
        err = io.StringIO()
        with redirect_stderr(err):                # the command's own entry, in process (an interpreter start is 5 s)
            code = main(["calibrate", str(d), "--out", str(out), "--quiet"])
        stderr = err.getvalue()
        assert "Traceback" not in stderr
        if code == 0:
            assert sorted(p.name for p in out.iterdir()) == ["model.json", "report.html", "trajectory.csv"]
            text = (out / "model.json").read_text()
            assert "NaN" not in text and "Infinity" not in text
            m = json.loads(text)
            sensor = m["sensor_model"]
            assert sensor["channels"] and all(sensor[f"{ch}_sigma"] > 0 for ch in sensor["channels"])
            assert all(sensor[f"{ch}_sigma"] is None for ch in {"reading", "bearing"} - set(sensor["channels"]))
        else:
            assert code == 2, stderr
            assert len(stderr.strip().splitlines()) == 1, stderr
            assert not out.exists()
