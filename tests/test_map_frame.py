"""A moved landmark's fit in the map's own frame: the unmoved landmarks stay where the map says, the moved one
carries its offset, and the path follows without changing the likelihood (fit/frame.py)."""
import json
import warnings

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.fit.frame import moved
from casm_graph.graph import augmented as AU
from casm_graph.graph.problem import Problem
from casm_graph.models.effects.landmark_offset import LandmarkOffset
from casm_graph.models.model import Model, paper_start
from tests.worlds import generate_world


class Map:
    def __init__(self, xy):
        self.landmark_xy, self.landmark_ids = xy, np.arange(len(xy))


def shape_fit(n, rng):
    """A random map of ``n`` landmarks, one moved 0.1-0.5 m: the effect, the shape coordinates a fit finds, the truth."""
    effect = LandmarkOffset(Map(rng.uniform(-5, 5, (n, 2)) + rng.uniform(-5, 5, 2)))
    k, d, a = rng.integers(n), rng.uniform(0.1, 0.5), rng.uniform(-np.pi, np.pi)
    raw = np.zeros((n, 2))
    raw[k] = d * np.array([np.cos(a), np.sin(a)])
    return effect, effect.Q.T @ raw.ravel(), raw, k, d


@pytest.mark.parametrize("n", [6, 8])
def test_the_unmoved_landmarks_stay_on_the_map_and_the_moved_one_carries_its_offset(n):
    """The shape coordinates spread one landmark's move over all (the others off by about a fifth of it); in the
    frame the others are off by a tenth or less (the move's scale part stays) and never more than before."""
    rng = np.random.default_rng(n)
    before, after, own = [], [], []
    for _ in range(100):
        effect, theta, raw, k, d = shape_fit(n, rng)
        err = np.linalg.norm(effect.offsets(theta) - raw, axis=1) / d
        assert effect.reframe(theta) is not None
        err2 = np.linalg.norm(effect.offsets(theta) - raw, axis=1) / d
        before.append(np.sqrt(np.mean(np.delete(err, k) ** 2)))
        after.append(np.sqrt(np.mean(np.delete(err2, k) ** 2)))
        own.append(err2[k])
    before, after = np.array(before), np.array(after)
    assert np.all(after <= 1.05 * before)
    assert np.median(after) < 0.12 < 0.15 < np.median(before)
    assert np.median(own) < 0.15


def test_four_landmarks_keep_the_shape_frame_and_the_frame_survives_model_json():
    rng = np.random.default_rng(3)
    effect, theta, *_ = shape_fit(4, rng)
    assert effect.reframe(theta) is None and not np.any(effect.frame)
    effect, theta, *_ = shape_fit(7, rng)
    effect.reframe(theta)
    entry = json.loads(json.dumps(effect.describe(theta)))
    again = LandmarkOffset(Map(effect.xy))
    np.testing.assert_allclose(again.offsets(again.theta_of(entry)), effect.offsets(theta))
    assert not np.any(LandmarkOffset(Map(effect.xy)).frame)


def test_the_frame_leaves_the_likelihood_as_it_is(tmp_path):
    """The graph's cost of poses and offsets equals that of the poses moved with the frame and the same offsets."""
    generate_world("table", tmp_path / "log", 1.0, 0, None, min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    assert len(log.landmark_ids) >= 5
    model = paper_start(log)
    effects = AU.instantiate(["landmark_offset"], log)
    problem = Problem(log, model, effects)
    theta = problem.theta_noise.copy()
    s = problem.slices[0]
    theta[s] = np.random.default_rng(0).normal(0, 0.1, s.stop - s.start)
    poses = log.truth[:, 1:]
    cost = problem.cost(problem.state(poses, model, theta))
    g = effects[0].reframe(theta[s])
    assert np.abs(g).max() > 1e-3
    poses2, _ = moved(poses, np.ones_like(poses), g)
    assert problem.cost(problem.state(poses2, model, theta)) == pytest.approx(cost, rel=1e-9)


def test_a_calibration_with_a_moved_landmark_puts_the_path_in_the_maps_frame(tmp_path):
    """Independent continuous world, seed 5, a landmark 0.15 m off: the path's error against the truth is about
    what is left once it is turned and shifted onto the truth (the frame right), and the moved landmark is found."""
    truth = generate_world("continuous", tmp_path / "log", 3.0, 5, "landmark_offset", min_range=0.3)
    log = cg.load_log(tmp_path / "log")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = cg.calibrate(log, seed=5, effects=["landmark_offset"])
    path = np.column_stack([cal.trajectory["x"], cal.trajectory["y"]])
    world = log.truth[:, 1:3]
    raw = np.sqrt(np.mean(np.sum((path - world) ** 2, axis=1)))
    pc, wc = path.mean(0), world.mean(0)
    u, _, vt = np.linalg.svd((path - pc).T @ (world - wc))
    aligned = (path - pc) @ (u @ vt) + wc
    best = np.sqrt(np.mean(np.sum((aligned - world) ** 2, axis=1)))
    assert raw < 1.5 * best, (raw, best)
    geo = truth["geometry"]
    entry = cal.model.effects["landmark_offset"]
    found = np.array([entry[f"dx_{geo['landmark']}"], entry[f"dy_{geo['landmark']}"]])
    assert np.linalg.norm(found - [geo["dx"], geo["dy"]]) < 0.3 * truth["strength"]
    others = [np.hypot(entry[f"dx_{i}"], entry[f"dy_{i}"]) for i in log.landmark_ids if i != geo["landmark"]]
    assert max(others) < 0.2 * truth["strength"]
    data = cal.model.to_json()
    assert Model.from_json(data).effects["landmark_offset"]["frame"] == entry["frame"]
    data["effects"]["landmark_offset"]["frame"] = [0.01, 0.02]
    with pytest.raises(cg.LogError, match="frame"):
        Model.from_json(data)
