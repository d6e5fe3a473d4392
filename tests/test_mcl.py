"""MCL with dynamic motion models (Milstein & Wang) and the graph's joint per-region estimate.

The science check runs one 6-minute floor in CI and five 10-minute floors with CASM_FULL=1;
benchmarks/seed_baselines.py prints the full tables.
"""
import numpy as np
import pytest

from casm_graph import mcl
from casm_graph.cli import main
from casm_graph.simulate_floor import FloorConfig, region_of, simulate

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
def test_dynamic_motion_models_and_the_graph():
    seeds = range(5) if FULL else [2]
    minutes = 10 if FULL else 6
    default_worst = map_right = graph_right = graph_closer = var_closer = 0
    for seed in seeds:
        cfg = FloorConfig(minutes=minutes, seed=seed)
        log, truth = simulate(cfg)
        K_true = np.array(truth["motion_model"]["region_k"])
        d = mcl.drive_of(log)
        runs = {"default": mcl.run_mcl(d, cfg.size, cfg.grid, "default", seed=seed)}
        k_opt = mcl.fit_k(*runs["default"].pairs[:, :4].T)
        runs["static"] = mcl.run_mcl(d, cfg.size, cfg.grid, "static", k_static=k_opt, seed=seed)
        runs["global"] = mcl.run_mcl(d, cfg.size, cfg.grid, "global", seed=seed)
        runs["regional"] = mcl.run_mcl(d, cfg.size, cfg.grid, "regional", seed=seed)
        err = {m: mcl.errors(r.poses, log.truth) for m, r in runs.items()}
        default_worst += all(err["default"][c] > err[m][c] for m in ("static", "global", "regional")
                             for c in ("range_error_pct", "angle_error_pct"))
        reg = runs["regional"]
        map_right += mcl.rough_regions(reg.k_final) == sorted(cfg.rough)
        g = mcl.graph_em(d, cfg.size, cfg.grid, reg.poses)
        graph_right += mcl.rough_regions(g.k) == sorted(cfg.rough)
        k_pairs = mcl.regional_fit(reg.pairs, len(K_true))
        graph_closer += mcl.log_error(g.k, K_true) <= min(mcl.log_error(reg.k_final, K_true),
                                                          mcl.log_error(k_pairs, K_true))
        var_closer += mcl.variance_error(g.k, K_true) <= min(mcl.variance_error(reg.k_final, K_true),
                                                             mcl.variance_error(k_pairs, K_true))
    n = len(seeds)
    print(f"default static worst on {default_worst}/{n}, MCL map right on {map_right}/{n}, "
          f"graph map right on {graph_right}/{n}, graph closer to the true k's on {graph_closer}/{n} "
          f"and to the true motion variances on {var_closer}/{n}")
    assert default_worst == n
    assert map_right >= (3 if FULL else 1)
    # one full-size seed lets the graph trade k_d against k_t (a k near zero, same variances): n - 1 there
    assert graph_right == n and var_closer == n and graph_closer >= n - (1 if FULL else 0)


def test_cli_simulates_the_floor(tmp_path):
    assert main(["simulate", str(tmp_path / "f"), "--protocol", "floor", "--minutes", "1"]) == 0
    assert (tmp_path / "f" / "observations.csv").is_file()
