"""A fleet on Dask (issue 24): many bundles calibrated at once, failures in their rows, second runs skip,
drift over time flags the robot that wears, and emcee runs on a Dask client through DaskPool."""
import csv
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from casm_graph import cli
from casm_graph.analysis import drift
from casm_graph.pipeline.fleet import DaskPool, calibrate_fleet, client_for, find_bundles, model_row, robot_and_time
from casm_graph.sim.fleet import simulate_fleet

from .conftest import FULL

DASK = Path(sys.executable).parent / "dask"


def rows_of(out: Path) -> list[dict]:
    with open(out / "fleet.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def four(tmp_path_factory) -> Path:
    """Four 2-minute aibo logs: robot00 and robot01, two days each."""
    root = tmp_path_factory.mktemp("fleet4") / "logs"
    simulate_fleet(root, robots=2, days=2, minutes=2, seed=3, wearing=0)
    return root


# --------------------------------------------------------------------------- finding bundles, robot and time

def test_find_bundles_and_robot_time(tmp_path, four):
    found = find_bundles(four)
    assert [b.relative_to(four).as_posix() for b in found] == \
        ["robot00/2026-03-01", "robot00/2026-03-02", "robot01/2026-03-01", "robot01/2026-03-02"]
    assert robot_and_time(found[1], four) == ("robot00", "2026-03-02")      # meta.json
    b = tmp_path / "r7" / "2026-01-05"                                      # the path ROBOT/DATE/
    b.mkdir(parents=True)
    for f in ("landmarks.csv", "commands.csv", "observations.csv"):
        shutil.copy(found[0] / f, b / f)
    (tmp_path / ".hidden" / "x").mkdir(parents=True)
    for f in ("landmarks.csv", "commands.csv", "observations.csv"):
        shutil.copy(found[0] / f, tmp_path / ".hidden" / "x" / f)
    assert find_bundles(tmp_path) == [b]
    assert robot_and_time(b, tmp_path) == ("r7", "2026-01-05")


# --------------------------------------------------------------------------- (a) a real scheduler and workers

def _start_cluster(tmp: Path):
    sched_file = tmp / "scheduler.json"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    procs = [subprocess.Popen([str(DASK), "scheduler", "--port", "0", "--no-dashboard", "--scheduler-file",
                               str(sched_file)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    deadline = time.time() + 60
    while not sched_file.is_file() and time.time() < deadline:
        time.sleep(0.2)
    assert sched_file.is_file(), "the dask scheduler did not start"
    for _ in range(2):
        procs.append(subprocess.Popen([str(DASK), "worker", "--scheduler-file", str(sched_file), "--nthreads", "1",
                                       "--nworkers", "1", "--no-dashboard"], env=env, cwd=tmp,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    return procs, sched_file


def _stop(procs):
    for p in reversed(procs):
        if p.poll() is None:
            p.terminate()
    for p in reversed(procs):
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_fleet_on_a_dask_scheduler_matches_standalone_calibrate(tmp_path, four):
    """fleet, diagnose and uncertainty on a scheduler and two workers started with Dask's own commands."""
    procs, sched_file = _start_cluster(tmp_path)
    try:
        from distributed import Client
        with Client(scheduler_file=str(sched_file), timeout="30s") as c:
            c.wait_for_workers(2, timeout=90)
        address = json.loads(sched_file.read_text())["address"]
        out = tmp_path / "out"
        assert cli.main(["fleet", four, "--out", out, "--scheduler", address, "--quiet"]) == 0
        first = find_bundles(four)[0].relative_to(four).as_posix()
        run = out / first
        candidates = ["--candidate", "battery_fade", "--candidate", "actuator_lag"]
        assert cli.main(["diagnose", four / first, "--model", run / "model.json", "--out", tmp_path / "dd",
                         "--scheduler", address, "--quiet", *candidates]) == 0
        assert cli.main(["uncertainty", four / first, "--model", run / "model.json", "--out", tmp_path / "uu",
                         "--scheduler", address, "--walkers", "12", "--max-steps", "100", "--quiet"]) == 0
    finally:
        _stop(procs)
    assert cli.main(["diagnose", four / first, "--model", run / "model.json", "--out", tmp_path / "dl",
                     "--workers", "1", "--quiet", *candidates]) == 0
    on_cluster, local = (json.loads((tmp_path / d / "diagnosis.json").read_text()) for d in ("dd", "dl"))
    assert on_cluster["verdict"] == local["verdict"]
    assert [(c["effect"], c["delta_bic"]) for c in on_cluster["candidates"]] == \
        [(c["effect"], c["delta_bic"]) for c in local["candidates"]]
    post = json.loads((tmp_path / "uu" / "posterior.json").read_text())
    assert all(all(map(math.isfinite, v["ci90"])) for v in post["parameters"].values())
    rows = rows_of(out)
    assert [r["path"] for r in rows] == [b.relative_to(four).as_posix() for b in find_bundles(four)]
    assert all(r["status"] == "ok" and r["error"] == "" for r in rows)
    assert len({r["worker"] for r in rows}) == 2                   # both workers took bundles
    assert all(not r["worker"].endswith(f":{os.getpid()}") for r in rows)
    assert all(int(r["steps"]) == 3600 and float(r["minutes"]) == pytest.approx(2.0, abs=0.01) for r in rows)
    data = json.loads((out / "fleet.json").read_text())
    assert len(data["rows"]) == 4 and data["scheduler"] == address
    assert "<img src=\"data:image/png;base64," in (out / "report.html").read_text()
    for r in rows[:1]:                                            # a bundle from the cluster against calibrate alone
        solo = tmp_path / "solo" / r["path"]
        assert cli.main(["calibrate", four / r["path"], "--out", solo, "--quiet"]) == 0
        a = json.loads((out / r["path"] / "model.json").read_text())
        b = json.loads((solo / "model.json").read_text())
        assert a["action_model"] == b["action_model"]
        assert a["sensor_model"] == b["sensor_model"]
    for r in rows:
        assert sorted(p.name for p in (out / r["path"]).iterdir()) == ["model.json", "report.html", "trajectory.csv"]


def test_unreachable_scheduler_is_one_line(tmp_path, four, capsys):
    assert cli.main(["fleet", four, "--out", tmp_path / "o", "--scheduler", "tcp://127.0.0.1:9", "--connect-timeout",
                     "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("casm-graph: error: --scheduler tcp://127.0.0.1:9: cannot connect") and "\n" not in err


# --------------------------------------------------------------------------- (b) a failing bundle, (c) second run

@pytest.fixture(scope="module")
def failing(tmp_path_factory, four):
    """Two good bundles and one with a non-numeric reading, calibrated once on a local cluster."""
    root = tmp_path_factory.mktemp("failing") / "logs"
    for rel in ("robot00/2026-03-01", "robot01/2026-03-01", "robot02/2026-03-01"):
        shutil.copytree(four / rel.replace("robot02", "robot01"), root / rel)
    (root / "robot02/2026-03-01/meta.json").unlink()
    obs = root / "robot02/2026-03-01/observations.csv"
    lines = obs.read_text().splitlines()
    cells = lines[5].split(",")
    cells[2] = "abc"
    lines[5] = ",".join(cells)
    obs.write_text("\n".join(lines) + "\n")
    out = root.parent / "out"
    first = calibrate_fleet(root, out, workers=2, progress=False)
    return root, out, first


def test_a_failing_bundle_gets_its_reason_and_the_others_complete(failing):
    _, out, first = failing
    by = {r["path"]: r for r in rows_of(out)}
    assert len(by) == 3
    bad = by["robot02/2026-03-01"]
    assert bad["status"] == "failed"
    assert "observations.csv" in bad["error"] and "row 5" in bad["error"] and "reading" in bad["error"]
    assert "\n" not in bad["error"]
    assert not (out / "robot02/2026-03-01").exists()
    for p in ("robot00/2026-03-01", "robot01/2026-03-01"):
        assert by[p]["status"] == "ok" and by[p]["error"] == ""
        assert (out / p / "model.json").is_file() and (out / p / "report.html").is_file()
    assert first.counts == {"ok": 2, "failed": 1, "skipped": 0}


def test_second_run_skips_completed_bundles(failing):
    root, out, first = failing
    before = {p: (out / p / "model.json").stat().st_mtime_ns for p in ("robot00/2026-03-01", "robot01/2026-03-01")}
    second = calibrate_fleet(root, out, workers=1, progress=False)
    assert second.counts == {"ok": 0, "failed": 1, "skipped": 2}
    for r1, r2 in zip(first.rows, second.rows):
        assert r1["path"] == r2["path"]
        if r1["status"] == "ok":
            assert r2["status"] == "skipped"
            for k in ("reading_sigma", "bearing_sigma", "mean_abs_vx", "log_likelihood", "iterations", "steps",
                      "reading_c2", "motion_noise_theta", "robot", "time"):
                assert r2[k] == r1[k], k
    assert before == {p: (out / p / "model.json").stat().st_mtime_ns for p in before}
    # a non-fleet, non-empty --out is refused before any work
    other = out.parent / "other"
    other.mkdir()
    (other / "x.txt").write_text("mine")
    assert cli.main(["fleet", root, "--out", other, "--quiet"]) == 2


# --------------------------------------------------------------------------- drift on hand-made models

def _table_model(scale=1.0, std=0.01, n=20, seed=0, gain=1.0):
    rng = np.random.default_rng(seed)
    vel = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n)])
    return {"action_model": {"kind": "table", "velocities": {str(a): (scale * v).tolist() for a, v in enumerate(vel)},
                             "std": {str(a): [std, std, 3 * std] for a in range(n)}},
            "motion_noise": [0.003, 0.003, 0.01],
            "sensor_model": {"reading_poly": [70 * gain, -44 * gain, 11.7 * gain, -1.1 * gain],
                             "reading_poly_std": [3, 3, 1, 0.1], "reading_sigma": 1.0, "bearing_sigma": 0.5,
                             "distance_range": [1.3, 4.1]},
            "effects": {}, "fit": {}}


def _command_model(scale=1.0, cmd=1.0):
    """A command map whose physical gain is ``scale``; ``cmd`` the log's largest command (model.json's scale)."""
    return {"action_model": {"kind": "command_poly", "scale": {"v": cmd, "w": 1.0},
                             "coefficients": {"v": [0.0, 0.4 * scale * cmd, 0.01 * cmd ** 2],
                                              "w": [0.0, 0.8 * scale]},
                             "std": {"v": [0.002, 0.003 * cmd, 0.003 * cmd ** 2], "w": [0.002, 0.004]}},
            "motion_noise": [0.01, 0.0, 0.01],
            "sensor_model": {"reading_poly": [0.0, 1.0], "reading_poly_std": [0.01, 0.005], "reading_sigma": 0.05,
                             "bearing_sigma": 0.02, "distance_range": [0.5, 5.0]}, "effects": {}, "fit": {}}


def test_drift_flags_a_scaled_table_and_reads_well():
    s = [drift.Session("robot 3", f"2026-03-0{d + 1}", f"r3/{d}", _table_model(scale=1 - 0.04 * d, seed=0))
         for d in range(3)]
    s += [drift.Session("robot 4", f"2026-03-0{d + 1}", f"r4/{d}", _table_model(seed=1, gain=1 + 0.001 * d))
          for d in range(3)]
    res = drift.analyse(s)
    assert res.drifted == {"robot 3": ["velocities"]}
    line = next(t for t in res.summary if t.startswith("robot 3"))
    assert "velocities scaled by 0.920 since 2026-03-01" in line and "beyond 3 sigma" in line
    assert all(f["robot"] == "robot 3" and f["family"] == "velocities" for f in res.flags)
    f = max((f for f in res.flags if f["comparison"] == "from_first"), key=lambda f: abs(f["sigma"]))
    assert re.fullmatch(r"robot 3: action \d+ (vx|vy|w) -8\.0 % since 2026-03-01 \(on 2026-03-03, \d+\.\d sigma\)",
                        f["text"]), f["text"]
    # noise figures are series, never flags; a tiny std does not flag a 1 % change
    assert res.series["robot 4"]["parameters"]["reading_sigma"]["family"] == "noise"
    tiny = [drift.Session("r", f"d{d}", f"{d}", _table_model(scale=1 + 0.01 * d, std=1e-6)) for d in range(2)]
    assert drift.analyse(tiny).flags == []


def test_drift_on_command_maps():
    s = [drift.Session("w1", f"2026-04-0{d + 1}", str(d), _command_model(scale=[1, 1, 0.9][d], cmd=[0.5, 0.6, 0.55][d]))
         for d in range(3)]
    res = drift.analyse(s)
    assert res.drifted == {"w1": ["command_map"]}
    assert any("command map scaled by 0.900" in t for t in res.summary)
    assert {f["parameter"] for f in res.flags} == {"v coef 1", "w coef 1"}


def test_command_maps_of_two_forms_are_not_compared():
    """A session whose turn map took its term in v (unequal wheels) against one without: the intercept absorbs
    the term differently, so no command-map figure is compared; two sessions with the term are."""
    base = _command_model()
    crossed = _command_model()
    crossed["action_model"].update(cross={"w": {"v": 0.3}}, cross_std={"w": {"v": 0.005}})
    crossed["action_model"]["coefficients"]["w"] = [-0.15, 0.8]      # the intercept the term took over
    res = drift.analyse([drift.Session("w2", "2026-04-01", "0", base), drift.Session("w2", "2026-04-02", "1", crossed)])
    assert res.drifted == {} and not res.flags
    moved = _command_model(scale=0.9)
    moved["action_model"].update(cross={"w": {"v": 0.3}}, cross_std={"w": {"v": 0.005}})
    res = drift.analyse([drift.Session("w2", "2026-04-01", "0", crossed), drift.Session("w2", "2026-04-02", "1", moved)])
    assert res.drifted == {"w2": ["command_map"]}


# --------------------------------------------------------------------------- emcee on a cluster

def test_dask_pool_runs_emcee_like_serial():
    import emcee

    def log_prob(x):                          # local: Dask sends it by value (cloudpickle)
        return -0.5 * float(np.sum((x - np.array([1.0, -2.0])) ** 2 / np.array([1.0, 0.25])))

    p0 = np.random.default_rng(0).normal(size=(8, 2))
    state = np.random.RandomState(5).get_state()
    serial = emcee.EnsembleSampler(8, 2, log_prob)
    serial.run_mcmc(emcee.State(p0, random_state=state), 40)
    with client_for(None, workers=2) as client:
        pool = DaskPool(client)
        assert pool.map(abs, [-1, 2, -3]) == [1, 2, 3] and pool.map(abs, []) == []
        pool = DaskPool(client)
        sampler = emcee.EnsembleSampler(8, 2, log_prob, pool=pool)
        sampler.run_mcmc(emcee.State(p0, random_state=state), 40)
    np.testing.assert_array_equal(sampler.get_chain(), serial.get_chain())
    assert pool.items == 8 + 40 * 8 and pool.calls == 1 + 2 * 40     # the start, then two half-ensembles a step


# --------------------------------------------------------------------------- (d) drift on a simulated fleet

@pytest.mark.science
def test_fleet_drift_flags_exactly_the_wearing_robots(tmp_path):
    robots, days, wearing, minutes = (20, 5, 2, 3) if FULL else (3, 3, 1, 2)
    logs, out = tmp_path / "fleet", tmp_path / "out"
    assert cli.main(["simulate-fleet", logs, "--robots", robots, "--days", days, "--wearing", wearing,
                     "--minutes", minutes, "--seed", 1]) == 0
    truth = json.loads((logs / "fleet_truth.json").read_text())
    assert len(truth["wearing"]) == wearing
    assert json.loads((logs / "robot00/2026-03-01/meta.json").read_text()) == {"robot": "robot00",
                                                                                 "time": "2026-03-01"}
    assert cli.main(["fleet", logs, "--out", out, "--quiet"]) == 0
    data = json.loads((out / "fleet.json").read_text())
    assert len(data["rows"]) == robots * days and all(r["status"] == "ok" for r in data["rows"])
    found = data["drift"]["drifted"]
    assert found == {r: ["velocities"] for r in truth["wearing"]}, data["drift"]["summary"]
    for r in truth["wearing"]:
        line = next(t for t in data["drift"]["summary"] if t.startswith(r + ": velocities scaled by"))
        k = float(line.split("scaled by ")[1].split()[0])
        assert k == pytest.approx(1 - truth["wear_per_day"] * (days - 1), abs=0.04)


def test_drift_names_a_curves_coefficients_by_their_variable():
    """Coefficients of a curve in d and of one in 1/d are not the same figure: drift and the fleet table say which."""
    m = {"sensor_model": {"reading_poly": [1.0, 2.0], "reading_poly_std": [0.1, 0.1], "reading_basis": "inverse_distance"}}
    assert {"reading c0 (inverse_distance)", "reading c1 (inverse_distance)"} <= set(drift.parameters(m))
    m["sensor_model"]["reading_basis"] = "distance"
    assert {"reading c0", "reading c1"} <= set(drift.parameters(m))
    assert model_row(m)["reading_basis"] == "distance"
