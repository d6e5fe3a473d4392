"""MCL with dynamic motion models (Milstein & Wang) and the graph's joint per-region estimates.

Two graph estimates: ``mcl.graph_em`` (EM on a GTSAM graph of built-in factors, known start and
sensor) and the catalog effect ``regional_motion_noise`` on the continuous-command calibration
(sensor curve, command map and trajectory learned with it, through the CLI). Regions are judged
where the true path spent at least ``MIN_SEGMENTS`` steps; elsewhere no method has data and every
estimate is its start. The science check runs one 6-minute floor in CI and five 10-minute floors with
CASM_FULL=1; benchmarks/seed_baselines.py prints the full tables.
"""
import json

import numpy as np
import pytest

from casm_graph.baselines import mcl
from casm_graph.cli import main
from casm_graph.fit import continuous
from casm_graph.fit.windows import WindowOptions
from casm_graph.io.log import write
from casm_graph.models.effects.regional_motion_noise import from_entry
from casm_graph.sim.floor import FloorConfig, region_of, simulate

from .conftest import FULL


def test_ml_recovers_k_from_motion_pairs():
    rng = np.random.default_rng(0)
    k = np.array([0.004, 0.01, 0.01])
    r_hat = rng.uniform(0.05, 0.3, 4000)
    t_hat = rng.uniform(-0.3, 0.3, 4000)
    vr, vt = mcl.variances(k, r_hat, t_hat)
    r = r_hat + rng.normal(size=4000) * np.sqrt(vr)
    t = t_hat + rng.normal(size=4000) * np.sqrt(vt)
    est = mcl.fit_k(r_hat, t_hat, r, t)
    assert np.all(np.abs(np.log(est / k)) < 0.15), est
    exp = mcl.fit_k_expected(r_hat, t_hat, (r - r_hat) ** 2, (t - t_hat) ** 2)
    assert np.all(np.abs(np.log(exp / est)) < 0.02), (exp, est)


def test_floor_noise_follows_the_region():
    cfg = FloorConfig(minutes=8, seed=5)
    log, truth = simulate(cfg)
    tr = log.truth[:, 1:]
    rel = np.array([np.cos(tr[:-1, 2]) * np.diff(tr[:, 0]) + np.sin(tr[:-1, 2]) * np.diff(tr[:, 1])])[0]
    r_hat = log.controls[:, 0] * log.dt
    reg = region_of(tr[:-1, :2], cfg.size, cfg.grid)
    rough = np.isin(reg, cfg.rough)
    z = (rel - r_hat) ** 2 / np.abs(r_hat)
    assert np.mean(z[rough]) / np.mean(z[~rough]) == pytest.approx(cfg.rough_factor, rel=0.35)


@pytest.mark.science
def test_dynamic_motion_models_and_the_graph(tmp_path):
    seeds = range(5) if FULL else [2]
    minutes = 10          # at 6 minutes MCL's regional map is right on 1 or 2 floors of 5 (chance), at 10 on all five
    default_worst = map_right = graph_right = graph_closer = var_closer = effect_right = effect_closer = 0
    for seed in seeds:
        cfg = FloorConfig(minutes=minutes, seed=seed)
        log, truth = simulate(cfg)
        K_true = np.array(truth["motion_model"]["region_k"])
        seen = mcl.regions_seen(log.truth, cfg.size, cfg.grid)
        d = mcl.drive_of(log)
        runs = mcl.run_modes(d, cfg.size, cfg.grid, seed=seed)
        err = {m: mcl.errors(r.poses, log.truth) for m, r in runs.items()}
        default_worst += mcl.default_worst(err, "range_error_pct") and mcl.default_worst(err, "angle_error_pct")
        reg = runs["regional dynamic"]
        map_right += mcl.map_right(reg.k_final, seen, cfg.rough)
        g = mcl.graph_em(d, cfg.size, cfg.grid, reg.poses)
        graph_right += mcl.map_right(g.k, seen, cfg.rough)
        k_pairs = mcl.regional_fit(reg.pairs, len(K_true))
        mcl_log = min(mcl.log_error(reg.k_final[seen], K_true[seen]), mcl.log_error(k_pairs[seen], K_true[seen]))
        mcl_var = min(mcl.variance_error(reg.k_final[seen], K_true[seen]),
                      mcl.variance_error(k_pairs[seen], K_true[seen]))
        graph_closer += mcl.log_error(g.k[seen], K_true[seen]) <= mcl_log
        var_closer += mcl.variance_error(g.k[seen], K_true[seen]) <= mcl_var
        bundle, run = tmp_path / f"floor{seed}", tmp_path / f"run{seed}"
        write(log, bundle)
        assert main(["calibrate", str(bundle), "--out", str(run), "--effect", "regional_motion_noise",
                     "--regions", f"{cfg.grid[0]},{cfg.grid[1]},0,0,{cfg.size[0]},{cfg.size[1]}", "--quiet"]) == 0
        entry = json.loads((run / "model.json").read_text())["effects"]["regional_motion_noise"]
        assert "Motion noise by region" in (run / "report.html").read_text()
        K_eff = from_entry(entry)[1]
        effect_right += mcl.map_right(K_eff, seen, cfg.rough)
        effect_closer += mcl.variance_error(K_eff[seen], K_true[seen]) <= mcl_var
        print(f"seed {seed}: motion variance error (log RMS) MCL {mcl_var:.2f}, graph_em "
              f"{mcl.variance_error(g.k[seen], K_true[seen]):.2f}, effect {mcl.variance_error(K_eff[seen], K_true[seen]):.2f}; "
              f"segments per region {entry['segments']}")
    n = len(seeds)
    print(f"default static worst on {default_worst}/{n}, MCL map right on {map_right}/{n}, "
          f"graph_em map right on {graph_right}/{n}, closer to the true k's on {graph_closer}/{n} "
          f"and to the true motion variances on {var_closer}/{n}; the regional_motion_noise effect map right on "
          f"{effect_right}/{n}, closer to the true motion variances on {effect_closer}/{n}")
    assert default_worst == n
    assert map_right >= (3 if FULL else 1)
    # one full-size seed lets the graph trade k_d against k_t (a k near zero, same variances): n - 1 there
    assert graph_right == n and var_closer == n and graph_closer >= n - (1 if FULL else 0)
    assert effect_right == n and effect_closer == n


@pytest.mark.science
def test_mcl_map_with_laser_like_sensing():
    """Every landmark in view seen on every step (the paper's laser, as near as our floor comes): MCL's own jitter
    shrinks and its regional map singles out the rough regions (18/20 ten-minute floors in BENCHMARKS.md, 8/20
    with the default camera-like sensing); default static stays the worst in range % (20/20)."""
    floors = [mcl.floor_trial(FloorConfig(minutes=10, seed=s, detect_prob=1.0)) for s in range(20 if FULL else 5)]
    right = sum(t["map_right"] for t in floors)
    worst = sum(t["default_worst"]["range_error_pct"] for t in floors)
    print(f"laser-like sensing: MCL map right on {right}/{len(floors)}, default static worst in range % on {worst}")
    assert right >= len(floors) - (3 if FULL else 1)
    assert worst == len(floors)


def test_range_start_slopes_are_tried_and_the_likeliest_goes_on():
    """A range sensor's start slope is picked by the log-likelihood after the held coarse rounds, among the
    ``SLOPE_STARTS`` slopes whose windows agree best (MRCLAM robot 4 needed it); model.json records them."""
    log, _ = simulate(FloorConfig(minutes=2, seed=1))
    init = continuous.initialise(log, continuous.start_model(log))
    slopes = [init.slope] + [a.slope for a in init.alternatives]
    assert len(set(slopes)) == WindowOptions().slope_starts
    fit = continuous.fit(log, marginals=False)
    tried = fit.model.fit["start_slopes"]
    assert [s for s, _ in tried] == pytest.approx(slopes, rel=1e-5)
    assert fit.notes["start_slope"] == pytest.approx(max(tried, key=lambda t: t[1])[0], rel=1e-5)


def test_cli_simulates_the_floor(tmp_path):
    assert main(["simulate", str(tmp_path / "f"), "--protocol", "floor", "--minutes", "1"]) == 0
    assert (tmp_path / "f" / "observations.csv").is_file()


def test_regional_motion_noise_is_refused_clearly_where_it_cannot_run(short_bundle, tmp_path, capsys):
    assert main(["calibrate", str(short_bundle[0]), "--out", str(tmp_path / "r"), "--effect",
                 "regional_motion_noise", "--quiet"]) == 2
    assert "continuous (v, w) commands" in capsys.readouterr().err and not (tmp_path / "r").exists()
    assert main(["simulate", str(tmp_path / "s"), "--effect", "regional_motion_noise=1"]) == 2
    assert "--protocol floor" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "f"), "--protocol", "floor", "--minutes", "1"]) == 0
    for bad in ("3", "0,2", "3,2,0,0,-1,8", "a,b"):
        assert main(["calibrate", str(tmp_path / "f"), "--out", str(tmp_path / "r"), "--effect",
                     "regional_motion_noise", "--regions", bad, "--quiet"]) == 2
        assert "--regions" in capsys.readouterr().err and not (tmp_path / "r").exists()


def test_regional_noise_problem_weights_each_segment_by_its_region():
    from casm_graph.fit import continuous as CT
    from casm_graph.graph.problem import Problem
    from casm_graph.models.effects.regional_motion_noise import Regions, entry, variances
    log, _ = simulate(FloorConfig(minutes=1, seed=0))
    m = CT.start_model(log).with_(command=CT.for_commands(log.controls, 2, 1, gain=1.0))
    k = np.array([[0.002, 0.01, 0.002]] * 6)
    k[4] = [0.02, 0.1, 0.02]
    regions = Regions((0.0, 0.0, 12.0, 8.0), (3, 2))
    m = m.with_(effects={"regional_motion_noise": entry(regions, k)})
    lay = CT.layout(log, CT.DEFAULTS.full_knot_dt)
    knots = log.truth[lay.knots, 1:]
    p = Problem(log, m, lay=lay, poses=knots)
    reg = region_of(knots[:-1, :2], (12.0, 8.0), (3, 2))
    np.testing.assert_array_equal(p.action.seg_region, reg)
    r = np.array([np.sum(np.abs(log.controls[lay.seg_idx[i], 0]) * lay.seg_dt[i]) for i in range(len(reg))])
    vr, _ = variances(k[reg], r, p.action.seg_turn)
    np.testing.assert_allclose(p.motion_sigma[:, 0], np.sqrt(vr), rtol=1e-9)
    with pytest.raises(ValueError, match="knot poses"):
        Problem(log, m, lay=lay)
