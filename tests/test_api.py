"""The public Python API (docs/log-format.md, "Python API") and the all-or-nothing output rules.

In memory first: ``cg.calibrate`` writes nothing; ``save`` writes what the command line writes, into a
new or empty directory only, completely or not at all; importing the package leaves matplotlib alone.
"""
import json
import os
import platform
import random
import signal
import subprocess
import sys
import time
import warnings
from importlib.metadata import entry_points

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.cli import main
from casm_graph.fit import continuous
from casm_graph.fit.residuals import sighting_residuals
from casm_graph.fit.result import Fit
from casm_graph.models.model import Model
from casm_graph.pipeline.calibrate import warn_if_worse
from casm_graph.sim.aibo import SimConfig, simulate, write

from .conftest import FULL


class HeadingSlip(cg.Effect):
    """Carpet pile: walking with the pile (+x) is faster than against it (the README's own effect)."""
    name = "heading_slip"
    channel = "motion"
    params = ("k",)
    start, scale = (0.0,), (0.05,)
    explains = (("forward", "heading"),)
    physics = "The carpet pile runs along x: forward speed scales by 1 + k cos(heading)."

    def velocity(self, theta, v, ctx):
        return v * (1.0 + theta[0] * np.cos(ctx["pose"][:, 2]))[:, None]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("api") / "log"
    log, truth = simulate(SimConfig(minutes=3, seed=1))
    write(log, truth, d)
    return d


@pytest.fixture(scope="module")
def cal(bundle):
    return cg.calibrate(cg.load_log(bundle))


def test_import_leaves_matplotlib_backend_alone():
    code = ("import importlib, pkgutil, matplotlib\n"
            "import casm_graph\n"
            "for m in pkgutil.walk_packages(casm_graph.__path__, 'casm_graph.'):\n"
            "    importlib.import_module(m.name)\n"
            "print(matplotlib.get_backend())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env={**os.environ, "MPLBACKEND": "svg"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "svg"


def test_the_command_keeps_freed_blocks_but_the_package_import_does_not():
    """The ``casm-graph`` executable sets glibc's mmap and trim thresholds (a fit's temporaries stay in the heap);
    importing the package leaves the process's allocator alone: a large block freed after import goes back to the
    kernel (the process's resident size falls), after ``steady_heap`` it stays."""
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("the heap setting is glibc's")
    code = ("import sys, numpy as np, casm_graph, casm_graph.cli as cli\n"
            "def rss():\n"
            "    return int(open('/proc/self/statm').read().split()[1])\n"
            "if sys.argv[1] == 'set':\n"
            "    assert cli.steady_heap()\n"
            "a = np.ones(50_000_000 // 8); before = rss(); del a\n"
            "print(before - rss())\n")
    freed = {how: int(subprocess.run([sys.executable, "-c", code, how], capture_output=True, text=True,
                                     check=True).stdout) for how in ("import", "set")}
    assert freed["import"] > 10_000 and freed["set"] < 1_000, freed     # pages returned: about 12,200 vs none
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "casm-graph"]
    assert script.value == "casm_graph.cli:command"


def test_public_names():
    for name in cg.__all__:
        assert hasattr(cg, name), name
    assert callable(cg.calibrate) and callable(cg.diagnose) and callable(cg.uncertainty)


def test_calibrate_in_memory_then_save_as_the_command_does(bundle, cal, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert list(tmp_path.iterdir()) == []                      # calibrate wrote nothing
    assert cal.model.fit["converged"]
    assert cal.trajectory.dtype.names == ("t", "x", "y", "theta", "sx", "sy", "stheta")
    assert len(cal.trajectory) == cal.log.steps + 1 and np.isfinite(cal.trajectory["sx"]).all()
    text = cal.summary()
    assert "reading sigma" in text and "bearing sigma" in text and "converged" in text
    cal.save(tmp_path / "run")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["model.json", "report.html", "trajectory.csv"]
    m = json.loads((tmp_path / "run" / "model.json").read_text())
    assert m["fit"]["options"] == {"method": "graph", "sensor_degree": 3, "seed": 0, "effects": [], "regions": None,
                                   "max_sensor_degree": 6, "sensor_basis": "auto", "cross_terms": "auto",
                                   "step_heading": "auto", "graph": {"coarse_stride": 10, "coarse_rounds": 6, "coarse_iterations": 5,
                                             "coarse_relax": 1.0, "realias_after": [2, 4], "full_iterations": 15,
                                             "full_rounds": 2, "sensor_curve": {"material": 0.1, "tail": 4.0,
                                                                                "suspect_pruned": 0.002, "margin": 10.0}},
                                   "command_graph": cg.CommandGraphOptions().to_json()}
    assert m["fit"]["log"] == str(bundle) and m["fit"]["version"]
    assert main(["calibrate", str(bundle), "--out", str(tmp_path / "cli"), "--quiet"]) == 0
    c = json.loads((tmp_path / "cli" / "model.json").read_text())
    assert c["action_model"] == m["action_model"] and c["sensor_model"] == m["sensor_model"]
    assert c["fit"]["command"].startswith("casm-graph calibrate")


def test_save_refuses_a_nonempty_directory_unless_forced(cal, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    with pytest.raises(cg.LogError, match="not empty"):
        cal.save(out)
    assert (out / "mine.txt").read_text() == "keep me"
    cal.save(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["model.json", "report.html", "trajectory.csv"]
    with pytest.raises(cg.LogError, match="input"):
        cal.save(cal.log.source, force=True)                     # never over the log itself
    with pytest.raises(cg.LogError):
        cal.save("")


def test_a_failure_while_writing_leaves_nothing(cal, tmp_path):
    def broken(path, c):
        path.write_text("<html>half")
        raise OSError("No space left on device")
    bad = cg.Calibration(log=cal.log, model=cal.model, trajectory=cal.trajectory, options=cal.options,
                         fit=cal.fit, write_report=broken)
    with pytest.raises(OSError):
        bad.save(tmp_path / "run")
    assert list(tmp_path.iterdir()) == []                        # neither the run nor its temporary sibling


def test_json_is_strict(cal, tmp_path):
    nan_model = cal.model.with_(fit={**cal.model.fit, "log_likelihood": float("nan")})
    cg.Calibration(log=cal.log, model=nan_model, trajectory=cal.trajectory, options=cal.options).save(tmp_path / "r")
    text = (tmp_path / "r" / "model.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text)["fit"]["log_likelihood"] is None


def test_user_effect_through_calibrate(bundle, cal):
    log = cg.load_log(bundle)
    with_slip = cg.calibrate(log, effects=[HeadingSlip])
    assert "heading_slip" in with_slip.model.effects
    assert np.isfinite(with_slip.model.effects["heading_slip"]["k"])
    assert with_slip.model_json["fit"]["options"]["effects"] == ["heading_slip"]


class PinnedSlip(HeadingSlip):
    """The carpet pile held at k = 0.5 by its prior: a model this log does not have (a fit stuck far from the data)."""
    name = "pinned_slip"
    start = (0.5,)

    def prior(self):
        return np.array([0.5]), np.array([1e-4])


def test_a_model_and_the_same_with_an_effect_compare(bundle, cal):
    """An action table's log-likelihood is taken on the graph its effects are fitted on: an effect the log lacks moves
    it by a few nats (the coarse graph's value read 64,346 against -5,492 with a fade added, a collapse to the eye),
    a lag the log has raises it by far more, and an effect pinned where the data are not lowers it, with a warning."""
    log = cg.load_log(bundle)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        slip = cg.calibrate(log, effects=[HeadingSlip])
    assert abs(slip.fit.log_likelihood - cal.fit.log_likelihood) < 30
    assert slip.model.fit["log_likelihood"] == slip.fit.log_likelihood
    assert cal.model.fit["log_likelihood"] == cal.fit.log_likelihood
    lagged, _ = cg.simulate("aibo", minutes=3, seed=1, effects={"actuator_lag": 0.3})
    gain = cg.calibrate(lagged, effects=["actuator_lag"]).fit.log_likelihood - cg.calibrate(lagged).fit.log_likelihood
    assert gain > 50
    with pytest.warns(RuntimeWarning, match="adding pinned_slip lowered the log-likelihood"):
        pinned = cg.calibrate(log, effects=[PinnedSlip])
    assert pinned.fit.log_likelihood < cal.fit.log_likelihood - 20
    # compared with the base refitted as the effect was, which on a log the base fits well is about the same
    assert abs(pinned.fit.notes["refit_log_likelihood"] - cal.fit.log_likelihood) < 30


def test_diagnose_and_uncertainty_from_a_calibration(bundle, cal, tmp_path):
    log = cg.load_log(bundle)
    strict = cg.DiagnoseOptions(structure_omega2=0.9)          # no residual structure counts: no unexplained verdict
    diag = cg.diagnose(log, cal, candidates=["battery_fade"], workers=1, options=strict)
    assert diag.verdict in {"none", "battery_fade"}
    assert diag.summary().startswith("verdict:")
    diag.save(tmp_path / "diag")
    saved = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert saved["verdict"] == diag.verdict and saved["options"] == strict.to_json()
    diag.candidates[0].implausible = "the floor would stop the robot's drive over part of the field"
    diag.save(tmp_path / "aside")                            # a fit set aside is marked where the candidates are listed
    assert "Set aside, not physical:</b> the floor would stop" in (tmp_path / "aside" / "report.html").read_text()
    assert json.loads((tmp_path / "aside" / "diagnosis.json").read_text())["candidates"][0]["implausible"]
    post = cg.uncertainty(log, cal, walkers=12, max_steps=60, seed=1)
    assert set(post.intervals) >= {"reading_sigma", "bearing_sigma"}
    post.save(tmp_path / "unc")
    assert {"posterior.json", "model.json", "corner.png", "trace.png", "report.html"} <= \
        {p.name for p in (tmp_path / "unc").iterdir()}


def test_unusable_out_is_refused_before_any_work(bundle, tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    t0 = time.perf_counter()
    assert main(["calibrate", str(bundle), "--out", str(f), "--quiet"]) == 2
    assert main(["calibrate", str(bundle), "--out", "", "--quiet"]) == 2
    assert main(["uncertainty", str(bundle), "--model", str(tmp_path / "nope" / "model.json"),
                 "--out", str(tmp_path / "nope")]) == 2
    assert time.perf_counter() - t0 < 30                         # refused at once, not after a fit
    err = capsys.readouterr().err
    assert "not a directory" in err and "Traceback" not in err


@pytest.mark.parametrize("command", ["calibrate", "diagnose"])
def test_a_signal_at_a_random_moment_leaves_out_absent_or_complete(bundle, tmp_path, command):
    """SIGTERM at random moments: --out is absent or complete, no temporary sibling, no worker left running."""
    psutil = pytest.importorskip("psutil")
    run = tmp_path / "base"
    assert main(["calibrate", str(bundle), "--out", str(run), "--quiet"]) == 0
    rng = random.Random(7 if command == "calibrate" else 8)
    expected = {"calibrate": {"model.json", "trajectory.csv", "report.html"},
                "diagnose": {"diagnosis.json", "report.html"}}[command]
    for trial in range(3):
        out = tmp_path / f"{command}{trial}"
        args = [command, str(bundle), "--out", str(out), "--quiet"]
        if command == "diagnose":
            args += ["--model", str(run / "model.json"), "--candidate", "battery_fade", "--candidate", "actuator_lag"]
        p = subprocess.Popen([sys.executable, "-m", "casm_graph.cli", *args], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        time.sleep(rng.uniform(1.5, 12.0))
        children = [c.pid for c in psutil.Process(p.pid).children(recursive=True)] if p.poll() is None else []
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        assert "Traceback" not in err
        if out.exists():
            assert {q.name for q in out.iterdir()} == expected
        elif p.returncode != -signal.SIGTERM:      # a signal during start-up (imports) kills before the handler
            assert p.returncode == 1 and "nothing written" in err
        assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".")] == []
        time.sleep(0.5)
        assert not [c for c in children if psutil.pid_exists(c) and psutil.Process(c).status() != "zombie"]


def test_graph_options_are_passed_in_and_recorded(bundle, cal):
    quick = cg.GraphOptions(coarse_rounds=2, realias_after=(1,), full_rounds=1, full_iterations=5)
    fast = cg.calibrate(cg.load_log(bundle), graph=quick)
    assert fast.model_json["fit"]["options"]["graph"] == {**quick.to_json(), "realias_after": [1]}
    # the search the options ask for ran: fewer LM iterations than the default's, a model still near it
    assert fast.fit.stages.count("coarse") <= 2 * quick.coarse_iterations
    assert fast.fit.iterations < cal.fit.iterations
    assert np.sqrt(np.mean((fast.model.velocities - cal.model.velocities) ** 2)) < 0.05


def test_command_graph_options_are_passed_in_and_recorded():
    """A continuous-command calibration searches as ``cg.CommandGraphOptions`` say and records them."""
    log, _ = cg.simulate("floor", minutes=2, seed=0)
    quick = cg.CommandGraphOptions(coarse_rounds=2, coarse_iterations=4, full_knot_dt=0.5, full_rounds=1,
                                   full_settle=0)
    cal = cg.calibrate(log, command_graph=quick)
    fit = cal.model_json["fit"]
    assert fit["options"]["command_graph"] == quick.to_json() and fit["knot_dt"] == 0.5
    assert cal.fit.stages.count("coarse") <= quick.coarse_rounds * quick.coarse_iterations
    assert "full" in cal.fit.stages and cal.fit.stages.count("full") <= quick.full_iterations
    v = cal.model.command.velocities(log.controls, log.dt)
    assert np.all(np.isfinite(v)) and np.corrcoef(v[:, 0], log.controls[:, 0])[0, 1] > 0.9


def test_one_calibration_page_for_every_kind_of_action_model(cal, tmp_path):
    """The same page for an action table and a command map: the same sections in the same order, the action
    model's own between the fit and the sensor; the residuals through the model's sensor effects (a lens fitted on
    the table log moves its reading residuals)."""
    import re

    floor_log, _ = cg.simulate("floor", minutes=2, seed=0)
    floor = cg.calibrate(floor_log, command_graph=cg.CommandGraphOptions(full_knot_dt=0.5, full_rounds=1))
    heads = {}
    for name, c in (("table", cal), ("floor", floor)):
        c.save(tmp_path / name)
        heads[name] = re.findall(r"<h2>([^<]*)</h2>", (tmp_path / name / "report.html").read_text())
    assert "Action table" in heads["table"] and "Command maps" in heads["floor"]
    common = [h for h in heads["table"] if h != "Action table"]
    assert common == [h for h in heads["floor"] if h != "Command maps"]
    assert heads["table"].index("Action table") == heads["floor"].index("Command maps") == common.index("Sensor model")
    lens = cg.calibrate(cal.log, effects=["lens_distortion"])
    poses = lens.fit.poses[cal.log.obs_step]
    through = sighting_residuals(cal.log, poses, lens.model,
                                            [k(cal.log) for k in lens.fit.notes["hooked_effects"]])["reading"]
    plain = sighting_residuals(cal.log, poses, lens.model)["reading"]
    assert [k.name for k in lens.fit.notes["hooked_effects"]] == ["lens_distortion"]
    assert np.nanmax(np.abs(through - plain)) > 0


def test_what_follows_a_calibration_rebuilds_its_graph(tmp_path):
    """Diagnosis, uncertainty and the truth check rebuild the graph on the knots the model was calibrated with
    (model.json ``fit.options.command_graph``, else ``fit.knot_dt``), not on the defaults; a bad recorded
    spacing is one LogError."""
    log, _ = cg.simulate("floor", minutes=2, seed=0)
    quick = cg.CommandGraphOptions(coarse_rounds=2, coarse_iterations=4, coarse_knot_dt=2.0, full_knot_dt=0.5,
                                   full_rounds=1, full_settle=0)
    cal = cg.calibrate(log, command_graph=quick)
    cal.save(tmp_path / "run")
    loaded = Model.load(tmp_path / "run" / "model.json")
    assert continuous.options_of(loaded) == quick
    assert continuous.options_of(cal.model).full_knot_dt == 0.5                  # in memory: fit.knot_dt
    assert continuous.options_of(cal.model.with_(fit={})) == continuous.DEFAULTS
    fine = continuous.layout(log, 0.5)
    diag = cg.diagnose(log, loaded, poses=np.column_stack([cal.trajectory[k] for k in ("x", "y", "theta")]),
                       candidates=["battery_fade"])
    assert len(diag.residuals["forward"].residual) == fine.n_poses - 1    # one motion residual per fine segment
    bad = loaded.with_(fit={**loaded.fit, "options": {"command_graph": {"full_knot_dt": -1}}})
    with pytest.raises(cg.LogError, match="full_knot_dt"):
        continuous.options_of(bad)


class WindowGlare(cg.Effect):
    """The notebook's glare: readings grow by 1 + k cos(heading) (sunlight from a window on the +x side)."""
    name = "window_glare"
    channel = "sensor"
    params = ("k",)
    start, scale = (0.0,), (0.02,)
    explains = (("reading", "heading"),)
    physics = "Sunlight from a window bleeds into the beacon's blob when the robot faces it."

    def reading(self, theta, predicted, ctx):
        return predicted * (1.0 + theta[0] * np.cos(ctx["pose"][:, 2]))


@pytest.mark.science
def test_a_users_sensor_effect_is_named_once_available_and_the_error_falls():
    """find_the_missing_effect.ipynb's glare (k = 0.1, six minutes, seed 3): the base absorbs it out of the residual
    tests' sight, but given the user's class the diagnosis names it, its fit finds k within 0.01 of the truth and the
    model's error falls (3.3 / 6.4 / 5.9 times the paper's tolerance on vx / vy / curve before, under 1.5 after).
    CI tries the glare beside landmark_offset, the catalog's best candidate at k = 0.2; full size, every effect."""
    log, truth = cg.simulate("aibo", minutes=6, seed=3, effects={"window_glare": 0.1}, extra_effects=(WindowGlare,))
    base = cg.calibrate(log, seed=3)
    d = cg.diagnose(log, base, extra_effects=[WindowGlare],
                    candidates=None if FULL else ["window_glare", "landmark_offset"])
    assert d.verdict == "window_glare", d.words
    fixed = cg.calibrate(log, effects=[WindowGlare], seed=3)
    assert fixed.model.effects["window_glare"]["k"] == pytest.approx(0.1, abs=0.01)
    before, after = cg.model_error(base.model, truth), cg.model_error(fixed.model, truth)
    assert after["score"] < 0.3 * before["score"], (before, after)


def test_an_effect_fit_that_falls_keeps_its_best_round_and_says_so():
    """The glare at 0.2 (find_the_missing_effect.ipynb's closing words), two minutes: least squares from the base's
    poses rise for a round, then fall 79 nats below it (the base misfits the log: velocities 0.2 m/s off). The fit
    keeps the round it reached highest, so the model with the glare never reads below the base's, and warns."""
    log, _ = cg.simulate("aibo", minutes=2, seed=3, effects={"window_glare": 0.2}, extra_effects=(WindowGlare,))
    base = cg.calibrate(log, seed=3)
    with pytest.warns(RuntimeWarning, match="the fit's last round left the log-likelihood at"):
        glare = cg.calibrate(log, effects=[WindowGlare], seed=3)
    notes = glare.fit.notes
    assert notes["kept_round"] is not None
    assert glare.fit.log_likelihood > notes["last_log_likelihood"] + 20
    assert glare.fit.log_likelihood > base.fit.log_likelihood - 20
    assert glare.model.fit["log_likelihood"] == glare.fit.log_likelihood
    assert glare.model.fit["kept_round"] == notes["kept_round"]            # model.json records it


def test_a_base_that_misfits_badly_is_compared_refitted_as_the_effects_were():
    """Where a base refitted on the step graph as the effects were (``refit_log_likelihood``) reaches less than the
    base holding its own noise levels, and the effects' fit lies between the two, the warning says the figures part
    instead of blaming the effects; below the refit it blames them (figures of the glare at 0.2 on six minutes)."""
    notes = {"base_log_likelihood": -14_412.2, "refit_log_likelihood": -15_979.0}

    def fit(ll):
        return Fit(model=None, poses=np.zeros((1, 3)), pose_std=np.zeros((1, 3)), log_likelihood=ll, notes=notes)

    with pytest.warns(RuntimeWarning, match="the base misfits this log so badly that the two figures part"):
        warn_if_worse(fit(-15_600.3), [WindowGlare])
    with pytest.warns(RuntimeWarning, match="lowered the log-likelihood from -15,979.0 to -16,100.0"):
        warn_if_worse(fit(-16_100.0), [WindowGlare])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warn_if_worse(fit(-14_400.0), [WindowGlare])
