"""Log bundles: round trip, and every bad input of INTERFACE section 1 rejected with file, row, column."""
import shutil

import numpy as np
import pytest

from casm_graph.cli import main
from casm_graph.io.log import LogError, load


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
