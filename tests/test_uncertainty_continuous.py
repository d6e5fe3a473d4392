"""Issues 20 and 22: ``uncertainty`` on continuous-command logs (``v,w``), both sensor channels or one.

The Laplace marginal likelihood of the command-map graph against a dense brute-force evaluation, its
maximum against the calibrated noise levels, the posterior's 90 % intervals against the floor
simulator's true sensor sigmas, the command line, and a range-only log through ``cg.uncertainty``.
"""
import json
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import minimize

import casm_graph as cg
from casm_graph.analysis.likelihood import command_poly as U
from casm_graph.cli import main
from casm_graph.fit import continuous as CT
from casm_graph.graph.problem import Problem
from casm_graph.models.command_model import for_commands
from casm_graph.models.model import Model
from casm_graph.analysis.posterior import SamplerOptions
from casm_graph.pipeline.uncertainty import compute

TRUE_RANGE_SIGMA, TRUE_BEARING_SIGMA = 0.05, 0.02      # the floor simulator's defaults
SENSOR = ("reading_sigma", "bearing_sigma")


@pytest.fixture(scope="module")
def floor():
    """A 4-minute floor log (range and bearing) with its truth, calibrated."""
    log, truth = cg.simulate("floor", minutes=4, seed=1)
    return SimpleNamespace(log=log, truth=truth, fit=CT.fit(log, marginals=False))


@pytest.fixture(scope="module")
def floor_ml(floor):
    return U.continuous_likelihood(floor.log, floor.fit.model, floor.fit.poses)


def tiny():
    """A 1-minute floor log and a model near its truth (identity command maps, range = distance)."""
    log, _ = cg.simulate("floor", minutes=1, seed=3)
    model = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)),
                  reading_poly=np.array([0.0, 1.0, 0.0, 0.0]), reading_sigma=0.05, bearing_sigma=0.02,
                  motion_noise=np.array([0.02, 0.005, 0.05]),
                  command=for_commands(log.controls, 2, 1, gain=1.0), channels=log.channels)
    return log, model


def dense_laplace(ml, x) -> tuple[float, np.ndarray, np.ndarray]:
    """log p(O | x) and the parameters' shift and covariance from the graph built afresh at noise levels ``x``
    (Gaussian sightings: no Huber weights), with a dense information matrix, log det and solves."""
    sr, sb, mot, _ = ml._split(x)
    pb = ml.problem
    m = ml.model.with_(reading_sigma=sr, bearing_sigma=sb, motion_noise=mot)
    problem = Problem(pb.log, m, pb.effects, lay=pb.lay, gate=(pb.r_sel, pb.b_sel), huber=False)
    A, e, groups = problem.jacobian(ml.state)
    A = A.toarray()
    sigma = np.concatenate([problem.motion_sigma.ravel(), np.full(len(groups["reading"]), sr),
                            np.full(len(groups["bearing"]), sb)])
    data = len(sigma)
    ldata = (-0.5 * float(e[:data] @ e[:data]) - float(np.sum(np.log(sigma))) - 0.5 * data * np.log(2 * np.pi)
             - 0.5 * float(e[data:] @ e[data:]))
    H, g = A.T @ A, A.T @ e
    sign, logdet = np.linalg.slogdet(H)
    assert sign > 0
    step = np.linalg.solve(H, g)
    par = ml.par
    return ldata + 0.5 * float(g @ step) - 0.5 * logdet, -step[par], np.linalg.inv(H)[np.ix_(par, par)]


def test_laplace_equals_a_dense_evaluation():
    """Each channel's rows re-weighted on one sparse pattern and factored by SuperLU in the chain order give the
    same log p(O | x), parameter shift and covariance as the graph rebuilt at x and solved densely."""
    log, model = tiny()
    ml = U.continuous_likelihood(log, model, log.truth[:, 1:], iterations=5)
    assert ml.names == ["reading_sigma", "bearing_sigma", "motion_noise_forward", "motion_noise_lateral",
                        "motion_noise_turn"]
    for f in ([1.0, 1.0, 1.0, 1.0, 1.0], [1.3, 0.8, 0.6, 2.0, 1.4]):
        x = ml.x_map * np.array(f)
        dense, shift, cov = dense_laplace(ml, x)
        assert ml(x) == pytest.approx(dense, abs=1e-6, rel=1e-10)
        s, C = ml.parameter_moments(x)
        np.testing.assert_allclose(s, shift, rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(C, cov, rtol=1e-6, atol=1e-14)


def test_likelihood_peaks_at_the_calibrated_noise(floor, floor_ml):
    """calibrate's noise levels (residuals corrected for the degrees of freedom the fit used) sit at the
    marginal likelihood's maximum: within 10 % for the sensor sigmas and the forward and turn noise. The
    floor robot never slips sideways, so the likelihood is flat below the calibrated lateral noise."""
    ml = floor_ml
    res = minimize(lambda u: -ml(np.exp(u)), np.log(ml.x_map), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 3000})
    ratio = dict(zip(ml.names, np.exp(res.x) / ml.x_map))
    for name in ("reading_sigma", "bearing_sigma", "motion_noise_forward", "motion_noise_turn"):
        assert abs(ratio[name] - 1) < 0.1, ratio
    assert ratio["motion_noise_lateral"] < 1.0
    assert -res.fun - ml(ml.x_map) < 1.0                     # the calibrated levels are within a nat of the top
    for i, name in enumerate(ml.names):                      # and a factor 1.5 off costs many nats (not flat)
        if name != "motion_noise_lateral":
            x = ml.x_map.copy()
            x[i] *= 1.5
            assert ml(x) < ml(ml.x_map) - 5, name


def drawn_noise(log) -> dict:
    """The std of the noise the simulator drew into this log's readings and bearings (true distance and bearing
    from the truth poses): what its sightings say of the sensor sigmas."""
    p = log.truth[log.obs_step, 1:]
    rel = log.landmark_xy[log.landmark_index] - p[:, :2]
    r = log.obs_reading - np.hypot(rel[:, 0], rel[:, 1])
    b = np.angle(np.exp(1j * (log.obs_bearing - np.arctan2(rel[:, 1], rel[:, 0]) + p[:, 2])))
    return {"reading_sigma": float(np.nanstd(r)), "bearing_sigma": float(np.nanstd(b))}


def test_posterior_covers_the_true_sensor_sigmas(floor):
    """The 90 % intervals contain the std of the noise drawn into the log, and the simulator's range sigma (0.05 m)
    and bearing sigma (0.02 rad) within the interval's width more (this log's 438 readings drew a std of 0.0454,
    2.7 of its own standard errors under 0.05); the command map and polynomial get Laplace std, and the map's band
    contains the truth (velocity = command)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # 1200 steps may fall short of 50 tau: warned, not wrong
        unc = compute(floor.log, floor.fit.model, floor.fit.poses, truth=floor.truth,
                      options=SamplerOptions(max_steps=1200), seed=2)
    iv = unc.intervals
    drawn = drawn_noise(floor.log)
    for name, true in (("reading_sigma", TRUE_RANGE_SIGMA), ("bearing_sigma", TRUE_BEARING_SIGMA)):
        lo, hi = iv[name]["ci90"]
        assert lo <= drawn[name] <= hi, (name, drawn, iv)
        assert lo - (hi - lo) <= true <= hi + (hi - lo), (name, iv)
    assert np.max(unc.chain.tau) < unc.chain.steps / 20          # at least 20 autocorrelation times long
    cm = unc.model.command
    assert np.all(cm.v_std > 0) and np.all(cm.w_std > 0)
    v = np.quantile(floor.log.controls[:, 0], [0.25, 0.5, 0.75])
    controls = np.column_stack([v, np.zeros(3)])
    bv = cm.basis(controls)[0]
    sd = np.sqrt(np.einsum("ni,ij,nj->n", bv, unc.cov_theta[:cm.n_v, :cm.n_v], bv))
    assert np.all(np.abs(bv @ cm.v_coef - v) < 3 * sd + 0.01)
    assert unc.model.reading_poly_cov.shape == (4, 4) and np.all(unc.model.reading_poly_std > 0)


def test_cli_writes_posterior_and_model(floor, tmp_path, capsys):
    """casm-graph uncertainty on a continuous-command bundle (no trajectory.csv: the start is a fresh fit)."""
    cg.write_log(floor.log, tmp_path / "log", floor.truth)
    (tmp_path / "run").mkdir()
    floor.fit.model.save(tmp_path / "run" / "model.json")
    out = tmp_path / "unc"
    rc = main(["uncertainty", str(tmp_path / "log"), "--model", str(tmp_path / "run" / "model.json"),
               "--out", str(out), "--max-steps", "200", "--quiet"])
    assert rc == 0
    capsys.readouterr()
    post = json.loads((out / "posterior.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    names = ["reading_sigma", "bearing_sigma", "motion_noise_forward", "motion_noise_lateral", "motion_noise_turn"]
    assert post["schema"] == "casm-graph/posterior/1" and list(post["parameters"]) == names
    assert set(post["sampler"]["autocorr_time"]) == set(names)
    assert "command map" in post["likelihood"]["integrated_out"]
    lap = post["laplace"]
    assert len(lap["command_std"]["v"]) == 3 and len(lap["command_std"]["w"]) == 2 and "reading_band" in lap
    m = json.loads((out / "model.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    assert m["action_model"]["kind"] == "command_poly"
    assert all(s > 0 for s in m["action_model"]["std"]["v"] + m["action_model"]["std"]["w"])
    assert len(m["sensor_model"]["reading_poly_std"]) == 4 and "reading_band" in m["sensor_model"]
    assert m["sensor_model"]["reading_sigma"] == pytest.approx(post["parameters"]["reading_sigma"]["median"])
    Model.load(out / "model.json")
    for f in ("corner.png", "trace.png", "report.html"):
        assert (out / f).stat().st_size > 1000
    assert "Command maps" in (out / "report.html").read_text()


def test_range_only_log_samples_no_bearing_sigma(tmp_path):
    """A range-only log through cg.calibrate and cg.uncertainty: no bearing sigma anywhere, the range sigma's
    interval around the truth."""
    log, truth = cg.simulate("floor", minutes=4, seed=1, sensor="range")
    cal = cg.calibrate(log)
    with pytest.warns(RuntimeWarning, match="too short"):
        unc = cg.uncertainty(log, cal, max_steps=300, seed=1)
    assert unc.chain.names == ["reading_sigma", "motion_noise_forward", "motion_noise_lateral", "motion_noise_turn"]
    lo, hi = unc.intervals["reading_sigma"]["ci90"]
    assert lo <= TRUE_RANGE_SIGMA <= hi
    unc.save(tmp_path / "unc")
    post = json.loads((tmp_path / "unc" / "posterior.json").read_text())
    assert "bearing_sigma" not in post["parameters"]
    sm = json.loads((tmp_path / "unc" / "model.json").read_text())["sensor_model"]
    assert sm["channels"] == ["reading"] and sm["bearing_sigma"] is None and sm["reading_sigma"] > 0
    with pytest.raises(cg.LogError, match="not a noise level of this model"):
        cg.uncertainty(log, cal, priors=("bearing_sigma=lognormal:0.02:1",), max_steps=100)


def test_a_table_model_on_a_continuous_log_says_why(floor):
    table = Model(action_ids=np.array([1]), velocities=np.zeros((1, 3)), reading_poly=np.array([0.0, 1.0]),
                  reading_sigma=0.05, bearing_sigma=0.02)
    with pytest.raises(cg.LogError, match="no command map .* calibrate this log first"):
        cg.uncertainty(floor.log, table)
