"""A tried-and-not-kept MCL variant (issue 6): regional motion pairs from the particles' own sampled motions.

    OPENBLAS_NUM_THREADS=1 python benchmarks/mcl_particle_pairs.py --kind mean
    OPENBLAS_NUM_THREADS=1 python benchmarks/mcl_particle_pairs.py --kind expected

Regional dynamic MCL as ``mcl.run_mcl``, but each step's pair is made ``lag`` steps later from the motions the
surviving particles drew at that step (their ancestry is carried through resampling): ``mean``, their mean as
the corrected motion (a fixed-lag smoothed correction) fitted by ``mcl.fit_k``; ``expected``, their mean square
as the expected squared error, fitted by ``mcl.fit_k_expected`` (a particle EM step per refit). Prints, per
camera-like 10-minute floor, the rough regions the final map picks out (judged as in seed_baselines.py).
"""
import argparse

import numpy as np

from casm_graph.baselines import mcl
from casm_graph.sim.floor import FloorConfig, region_of, step
from casm_graph.sim.floor import simulate as simfloor


def run(drive, size, grid, kind: str, lag: int = 10, particles: int = 500, window: int = 300, refit_every: int = 25,
        min_pairs: int = 60, range_sigma: float = 0.05, bearing_sigma: float = 0.02, seed: int = 0) -> np.ndarray:
    """The final (R, 3) regional k's."""
    rng = np.random.default_rng(seed)
    K = np.tile(np.asarray(mcl.DEFAULT_K, float), (grid[0] * grid[1], 1))
    T = len(drive.r)
    P = np.tile(drive.start, (particles, 1))
    est = drive.start.copy()
    starts = np.searchsorted(drive.obs_step, np.arange(T + 2))
    er, et = np.zeros((lag, particles)), np.zeros((lag, particles))    # each particle's drawn errors, by ancestry
    meta = [None] * lag
    windows, new = {}, {}
    fit = mcl.fit_k_expected if kind == "expected" else mcl.fit_k
    for k in range(T):
        reg = region_of(est[:2], size, grid)[0]
        vr, vt = mcl.variances(K[reg], drive.r[k], drive.theta[k])
        nr, nt = rng.normal(size=particles) * np.sqrt(vr), rng.normal(size=particles) * np.sqrt(vt)
        P = step(P, drive.r[k] + nr, drive.theta[k] + nt)
        slot = k % lag
        if meta[slot] is not None:                  # the step lag ago: its pair from the survivors' draws
            rr, tt, g = meta[slot]
            pair = ((rr, tt, np.mean(er[slot] ** 2), np.mean(et[slot] ** 2)) if kind == "expected"
                    else (rr, tt, rr + er[slot].mean(), tt + et[slot].mean()))
            win = windows.setdefault(g, [])
            win.append(pair)
            if len(win) > window:
                win.pop(0)
            new[g] = new.get(g, 0) + 1
            if new[g] >= refit_every and len(win) >= min_pairs:
                K[g] = fit(*np.array(win).T, start=K[g])
                new[g] = 0
        er[slot], et[slot], meta[slot] = nr, nt, (drive.r[k], drive.theta[k], reg)
        idx = mcl.correction(P, drive, slice(starts[k + 1], starts[k + 2]), range_sigma, bearing_sigma, rng)
        if idx is not None:
            P, er, et = P[idx], er[:, idx], et[:, idx]
        est = mcl._mean_pose(P)
    return K


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kind", choices=("mean", "expected"), default="mean")
    ap.add_argument("--lag", type=int, default=10)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    a = ap.parse_args()
    right = 0
    for seed in a.seeds:
        cfg = FloorConfig(seed=seed, minutes=10.0)
        log, truth = simfloor(cfg)
        K_true = np.array(truth["motion_model"]["region_k"])
        K = run(mcl.drive_of(log), cfg.size, cfg.grid, a.kind, lag=a.lag, seed=seed)
        seen = mcl.regions_seen(log.truth, cfg.size, cfg.grid)
        right += mcl.map_right(K, seen, cfg.rough)
        print(f"seed {seed}: rough regions {mcl.rough_among(K, seen)} (true {sorted(cfg.rough)}), "
              f"RMS log(var/var_true) {mcl.variance_error(K[seen], K_true[seen]):.2f}", flush=True)
    print(f"{a.kind}, lag {a.lag}: map right on {right}/{len(a.seeds)}")


if __name__ == "__main__":
    main()
