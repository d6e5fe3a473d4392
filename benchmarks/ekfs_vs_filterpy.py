"""Seconds per EKFS E-step on the 27,000-step log: our compiled filter vs filterpy, side by side.

Ours: :func:`casm_graph.fit.ekfs.forward` + ``backward`` + ``smooth`` (numba). filterpy has an
``ExtendedKalmanFilter`` for the forward pass and a linear RTS smoother (``rts_smoother``) fed with
the per-step linearised F and Q; it has no backward information filter, so the comparison is
forward pass + smoother in each. Also times one whole EKFS-EM iteration and one graph-EM iteration.

    python benchmarks/ekfs_vs_filterpy.py [--minutes 15] [--whole]

``--whole`` also runs EKFS-EM to its stop rule and graph-EM to convergence from the paper's start.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, rts_smoother

from casm_graph.fit import ekfs
from casm_graph.fit.methods import METHODS
from casm_graph.fit.methods.ekfs_em import _observations
from casm_graph.fit.methods.graph_em import em_map
from casm_graph.models.model import paper_start
from casm_graph.sim.aibo import SimConfig, simulate


def setup(minutes):
    log, truth = simulate(SimConfig(minutes=minutes, seed=0))
    m = paper_start(log)
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids])
    m = m.with_(velocities=tv, reading_poly=np.array(truth["sensor_model"]["reading_poly_best_cubic"]),
                reading_sigma=1.0, bearing_sigma=0.5)
    return log, truth, m


def ours(log, m, sig):
    order, ptr, lm, zr, zb = _observations(log)
    u = m.velocity_of(log.action) * log.dt[:, None]
    use = np.ones(len(zr), bool)
    mu0, P0 = log.truth[0, 1:].copy(), np.diag([0.01, 0.01, 0.01])
    t = time.perf_counter()
    step_sig = ekfs.step_sigmas(sig, log)
    mu_a, P_a, ll, _ = ekfs.forward(mu0, P0, u, step_sig, ptr, lm, zr, zb, m.reading_poly, 1.0, 0.5, use)
    Lb, eb, Ld, ed = ekfs.backward(mu_a, u, step_sig, ptr, lm, zr, zb, m.reading_poly, 1.0, 0.5, use)
    mu_g, _ = ekfs.smooth(mu_a, P_a, Lb, eb)
    return time.perf_counter() - t, mu_g


def filterpy_estep(log, m, sig):
    order, ptr, lm, zr, zb = _observations(log)
    u = m.velocity_of(log.action) * log.dt[:, None]
    poly = m.reading_poly
    R = np.diag([1.0, 0.25])
    t = time.perf_counter()
    ekf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
    ekf.x = log.truth[0, 1:].copy()
    ekf.P = np.diag([0.01, 0.01, 0.01])
    K = log.steps + 1
    Xs, Ps, Fs, Qs = np.empty((K, 3)), np.empty((K, 3, 3)), np.empty((K, 3, 3)), np.empty((K, 3, 3))

    def hx(x, L):
        d = np.hypot(L[0] - x[0], L[1] - x[1])
        return np.array([np.polynomial.polynomial.polyval(d, poly), np.arctan2(L[1] - x[1], L[0] - x[0]) - x[2]])

    def hj(x, L):
        dx, dy = L[0] - x[0], L[1] - x[1]
        r2 = dx * dx + dy * dy
        d = np.sqrt(r2)
        df = np.polynomial.polynomial.polyval(d, np.polynomial.polynomial.polyder(poly))
        return np.array([[-df * dx / d, -df * dy / d, 0.0], [dy / r2, -dx / r2, -1.0]])

    def residual(a, b):
        r = a - b
        r[1] = (r[1] + np.pi) % (2 * np.pi) - np.pi
        return r

    for k in range(K):
        for j in range(ptr[k], ptr[k + 1]):
            ekf.update(np.array([zr[j], zb[j]]), hj, hx, R=R, args=(lm[j],), hx_args=(lm[j],), residual=residual)
        Xs[k], Ps[k] = ekf.x, ekf.P
        if k < K - 1:
            th = ekf.x[2]
            c, s = np.cos(th), np.sin(th)
            F = np.eye(3)
            F[0, 2], F[1, 2] = -s * u[k, 0] - c * u[k, 1], c * u[k, 0] - s * u[k, 1]
            Rt = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            Q = Rt @ np.diag(sig ** 2) @ Rt.T
            ekf.F, ekf.Q = F, Q
            ekf.x = ekf.x + Rt @ u[k]
            ekf.P = F @ ekf.P @ F.T + Q
            Fs[k], Qs[k] = F, Q
    Fs[-1], Qs[-1] = np.eye(3), np.eye(3) * 1e-9
    # filterpy's RTS smoother predicts with F @ x (a linear model); feed it the filtered means and
    # linearised F, Q as "where they apply": the smoothed means are then only approximate
    mu_s, _, _, _ = rts_smoother(Xs, Ps, Fs, Qs)
    return time.perf_counter() - t, mu_s


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=15)
    ap.add_argument("--whole", action="store_true", help="also time whole EKFS-EM and graph-EM runs")
    args = ap.parse_args()
    log, truth, m = setup(args.minutes)
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids])
    sig = np.array([0.01, 0.01, 0.1])
    ours(log, m, sig)                                  # compile once
    t_o, mu_o = ours(log, m, sig)
    t_f, mu_f = filterpy_estep(log, m, sig)
    err = lambda mu: np.sqrt(np.mean(np.sum((mu[:, :2] - log.truth[:, 1:3]) ** 2, 1)))  # noqa: E731
    print(f"| E-step, {log.steps} steps | ours (numba) | filterpy EKF + RTS | ratio |")
    print("|---|---|---|---|")
    print(f"| seconds | {t_o:.3f} | {t_f:.2f} | {t_f / t_o:.0f}x |")
    print(f"| smoothed position RMS error (m) | {err(mu_o):.3f} | {err(mu_f):.3f} | |")
    sec = METHODS["ekfs-em"](log, paper_start(log), max_iterations=11, patience=1000).notes["history"]["seconds"]
    print(f"\nEKFS-EM: {(sec[-1] - sec[0]) / (len(sec) - 1):.2f} s per iteration (10 iterations after the first, "
          "from the paper's start)")
    m2 = m.with_(motion_noise=np.array([0.002, 0.002, 0.004]))
    em_map(log, m2, log.truth[:, 1:])
    t = time.perf_counter()
    for _ in range(3):
        em_map(log, m2, log.truth[:, 1:])
    print(f"graph-EM: {(time.perf_counter() - t) / 3:.2f} s per EM iteration (E-step smoothing + chain marginals + M-step)")
    if args.whole:
        print("\n| whole run from the paper's start | iterations | seconds | s per iteration | vx, vy mm/s, w rad/s RMS |")
        print("|---|---|---|---|---|")
        for name in ("ekfs-em", "graph-em"):
            t = time.perf_counter()
            f = METHODS[name](log, paper_start(log))
            sec = time.perf_counter() - t
            rms = np.sqrt(np.mean((f.model.velocities - tv) ** 2, axis=0))
            print(f"| {name} | {f.iterations} | {sec:.0f} | {sec / max(f.iterations, 1):.2f} | "
                  f"{1000 * rms[0]:.1f}, {1000 * rms[1]:.1f}, {rms[2]:.3f} |", flush=True)


if __name__ == "__main__":
    main()
