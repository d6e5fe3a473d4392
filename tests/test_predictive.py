"""Predictive residuals: the open-loop run is exact for the right model and drifts for a wrong one."""
import numpy as np

from casm_graph.analysis.predictive import open_loop, predictive, robust_scale
from casm_graph.graph.table import integrate


def _track(seed=0, steps=600):
    rng = np.random.default_rng(seed)
    dt = np.full(steps, 0.05) + rng.uniform(0, 0.01, steps)
    v = np.column_stack([0.3 + 0.1 * np.sin(np.arange(steps) / 40), 0.05 * rng.standard_normal(steps),
                         0.8 * np.sin(np.arange(steps) / 25)])
    return integrate(np.array([1.0, -2.0, 2.5]), v * dt[:, None]), v, dt


def test_open_loop_of_the_true_velocities_is_the_trajectory_at_every_horizon():
    poses, v, dt = _track()
    for n in (0, 1, 10, 200, 10_000):
        p = open_loop(poses, v, dt, n)
        assert np.allclose(p[:, :2], poses[:, :2], atol=1e-9)
        assert np.allclose(np.angle(np.exp(1j * (p[:, 2] - poses[:, 2]))), 0.0, atol=1e-9)


def test_a_wrong_model_predicts_worse_the_longer_it_runs():
    poses, v, dt = _track(1)
    off = lambda traj: {"position": np.hypot(*(traj[:, :2] - poses[:, :2]).T)}
    right = predictive(poses, v, dt, off, horizons=(0.0, 0.5, 1.0, 2.0))
    wrong = predictive(poses, v * [1.1, 1.0, 0.9], dt, off, horizons=(0.0, 0.5, 1.0, 2.0))
    assert right["horizons_s"] == [0.0, 0.5, 1.0, 2.0]
    assert max(right["channels"]["position"]) < 1e-9
    e = wrong["channels"]["position"]
    assert e[0] < 1e-12 and all(b > a for a, b in zip(e, e[1:]))
    # 2 s at about 0.3 m/s, 10 % slow plus a turn-rate error: centimetres to decimetres
    assert 0.02 < e[-1] < 0.5


def test_horizons_beyond_a_tenth_of_the_log_are_left_out_and_nan_sightings_ignored():
    poses, v, dt = _track(2, steps=100)            # about 5.5 s of log
    out = predictive(poses, v, dt, lambda t: {"r": np.r_[np.nan, np.ones(len(t) - 1)]}, horizons=(0.0, 0.5, 5.0))
    assert out["horizons_s"] == [0.0, 0.5] and out["channels"]["r"] == [1.4826, 1.4826]
    assert np.isnan(robust_scale(np.array([np.nan])))
