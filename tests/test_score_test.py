"""The score test (analysis.score_test) against fitted gains, and the diagnosis's screen built on it."""
import numpy as np
import pytest

import casm_graph as cg
from casm_graph.analysis import diagnosis as D
from casm_graph.analysis.score_test import predicted_floor, predicted_gain
from casm_graph.fit import effect_fit
from casm_graph.graph.augmented import instantiate
from casm_graph.sim.aibo import SimConfig, simulate, write


@pytest.fixture(scope="module")
def lens_world(tmp_path_factory):
    """Three minutes with a weak lens distortion hidden (an effect linear in its parameter), calibrated without it,
    and the base fit a diagnosis scores candidates against."""
    d = tmp_path_factory.mktemp("lens")
    log, truth = simulate(SimConfig(minutes=3, seed=5, effects={"lens_distortion": 0.15}))
    write(log, truth, d)
    log = cg.load_log(d)
    cal = cg.calibrate(log, seed=5)
    poses = np.column_stack([cal.trajectory[k] for k in ("x", "y", "theta")])
    base = effect_fit.fit(log, cal.model, poses, [], rounds=2, iterations=8)
    return log, cal, base


def test_the_predicted_gain_is_the_fitted_one_at_fixed_noise(lens_world):
    """Least squares with the effect added (noise levels held) lowers the cost by what the score test predicted:
    the hidden lens within a quarter (its scale multiplies the sensor curve, so the gain is not quadratic in the
    parameters: 20.8 predicted against 26.3 here), an absent friction plane within a tenth of a nat; a noise-only
    effect has no test."""
    log, _, base = lens_world
    floor = predicted_floor(base.problem, base.state)
    assert floor <= base.problem.cost(base.state)
    gains = {}
    for name in ("lens_distortion", "surface_friction:1"):
        eff = instantiate([name], log)[0]
        gain = predicted_gain(log, base, eff, floor)
        f = effect_fit.fit(log, base.model, base.poses, [eff], rounds=1, iterations=30, fit_noise=False, rel_tol=1e-12)
        gains[name] = (gain, floor - f.cost[-1])
    lens, plane = gains["lens_distortion"], gains["surface_friction:1"]
    assert lens[1] > 20, gains                                 # the hidden effect is there to find
    assert abs(lens[0] - lens[1]) < 0.25 * lens[1], gains
    assert abs(plane[0] - plane[1]) < 0.1 and plane[0] < 2.0, gains
    assert predicted_gain(log, base, instantiate(["range_dependent_noise"], log)[0], floor) is None


def test_the_diagnosis_fits_only_what_the_screen_keeps(lens_world):
    """Screened members are recorded with the predicted delta BIC and no held-out score; the verdict and the
    fitted candidates are those of the unscreened diagnosis."""
    log, cal, _ = lens_world
    asked = ["lens_distortion", "surface_friction", "range_dependent_noise"]
    screened = cg.diagnose(log, cal, candidates=asked, workers=1)
    full = cg.diagnose(log, cal, candidates=asked, workers=1, options=D.DiagnoseOptions(screen_share=0.0))
    assert screened.verdict == full.verdict == "lens_distortion"
    by = {c.effect: c for c in screened.candidates}
    assert not by["lens_distortion"].screened and not by["range_dependent_noise"].screened
    friction = by["surface_friction"]
    assert friction.screened and np.isnan(friction.heldout_nll_drop) and friction.delta_bic > 0
    assert set(friction.orders) == {0, 1, 2, 3, 4}             # every member screened, each with its prediction
    assert friction.to_json()["screened"] is True and "score test" in friction.to_json()["heldout_skipped"]
    assert not any(c.screened for c in full.candidates)
    fitted = {c.effect: c.delta_bic for c in screened.candidates if not c.screened}
    assert fitted == pytest.approx({c.effect: c.delta_bic for c in full.candidates if c.effect in fitted})
