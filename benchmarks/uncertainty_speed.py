"""Cost of one marginal-likelihood evaluation p(O | noise levels), three ways, side by side on one log.

* EKF: the EKFS-EM paper's forward filter likelihood (numba), table and polynomial held fixed;
* Laplace, poses: the fixed-linearisation Laplace value with the pose chain re-factored (numba);
* Laplace, all: the same with the velocity table and polynomial integrated out too (what
  ``casm-graph uncertainty`` samples), by segment elimination.

Linearised at the simulator's truth (the cost does not depend on where). Median CPU time of
--repeat calls (single-threaded numba: CPU time is the wall time on an idle machine).

    python benchmarks/uncertainty_speed.py --minutes 2 8 15
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from casm_graph.analysis.likelihood import MarginalLikelihood, likelihood
from casm_graph.fit import ekfs
from casm_graph.fit.methods.ekfs_em import _observations
from casm_graph.models.model import Model
from casm_graph.sim.aibo import SimConfig, simulate


def truth_model(log, truth) -> Model:
    sm = truth["sensor_model"]
    ids = log.action_ids
    return Model(action_ids=ids, velocities=np.array([truth["action_model"]["velocities"][str(a)] for a in ids]),
                 reading_poly=np.array(sm["reading_poly_best_cubic"]), reading_sigma=sm["reading_sigma"],
                 bearing_sigma=sm["bearing_sigma"], motion_noise=np.array(truth["motion_noise"]),
                 distance_range=tuple(sm["distance_range"]))


def median_ms(f, x, repeat):
    """Median CPU time of one call (process time: other jobs on the machine do not inflate it)."""
    f(x)
    t = []
    for _ in range(repeat):
        t0 = time.process_time()
        f(x)
        t.append(time.process_time() - t0)
    return 1000 * float(np.median(t))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[2, 8, 15])
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args()
    print("| log | steps | EKF ms | Laplace, poses ms | Laplace, all ms | 20,000 evaluations (all) |  (CPU)")
    print("|---|---|---|---|---|---|")
    for minutes in args.minutes:
        log, truth = simulate(SimConfig(minutes=minutes, seed=0))
        model = truth_model(log, truth)
        ml = likelihood(log, model, log.truth[:, 1:], iterations=2)
        ml0 = MarginalLikelihood(ml.problem, ml.state, model, integrate_parameters=False)
        st = ml.state
        _, ptr, lm, z_r, z_b = _observations(log)
        u = st.velocities[np.searchsorted(model.action_ids, log.action)] * log.dt[:, None]
        use = np.ones(len(z_r), bool)

        def ekf(x):
            sr, sb, mot, _ = ml._split(x)
            return ekfs.forward(st.poses[0], np.diag([1e-2] * 3), u, ekfs.step_sigmas(mot, log), ptr, lm, z_r, z_b,
                                st.poly, sr, sb, use)[2]

        x = ml.x_map
        t_ekf, t_pose, t_all = (median_ms(f, x, args.repeat) for f in (ekf, ml0, ml))
        print(f"| {minutes:g} min | {log.steps} | {t_ekf:.1f} | {t_pose:.1f} | {t_all:.1f} | "
              f"{20000 * t_all / 1000:.0f} s |", flush=True)


if __name__ == "__main__":
    main()
