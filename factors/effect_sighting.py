"""Effect-augmented beacon-reading and bearing factors: the sighting as the sensor effects change it.

The sensor effects move where the robot and landmark really were (``geometry``) and what the
sensor reports (``reading``); derivatives with respect to the pose (body-frame tangent), the
polynomial and the effect parameters are central differences of one vectorised forward pass.
"""
from __future__ import annotations

import numpy as np

from .base import wrap
from .effect_motion import STEP, body_step


def error(fn, P, poly, theta, ls_index, ls_slices, obs_knot, r_idx, b_idx, z_reading, z_bearing,
          jacobians=True, velocity=None):
    """((reading error, J), (bearing error, J)); each error is predicted minus measured.

    ``velocity`` (n, 3), when the sensor effects use the robot's velocity (latency), adds the
    derivatives with respect to it (``J["velocity"]``) for the caller to chain into the table.
    """
    idx = np.arange(len(obs_knot))
    pose = P[obs_knot]
    pred, bearing, _ = fn(theta, pose, poly, idx)
    er = pred[r_idx] - z_reading[r_idx]
    eb = wrap(bearing[b_idx] - z_bearing[b_idx])
    if not jacobians:
        return (er, None), (eb, None)
    n = len(idx)
    Jp_r, Jp_b = np.empty((n, 3)), np.empty((n, 3))
    for c in range(3):
        pr_p, b_p, _ = fn(theta, body_step(pose, c, STEP), poly, idx)
        pr_m, b_m, _ = fn(theta, body_step(pose, c, -STEP), poly, idx)
        Jp_r[:, c] = (pr_p - pr_m) / (2 * STEP)
        Jp_b[:, c] = wrap(b_p - b_m) / (2 * STEP)
    Jc = np.empty((n, len(poly)))
    for c in range(len(poly)):
        q = poly.copy()
        q[c] += 1.0
        Jc[:, c] = fn(theta, pose, q, idx)[0] - pred           # the reading is linear in the polynomial
    mine = np.concatenate([np.arange(s.start, s.stop) for s in ls_slices] + [np.zeros(0, int)]).astype(int)
    Jt_r, Jt_b = np.zeros((n, len(ls_index))), np.zeros((n, len(ls_index)))
    for j, col in enumerate(ls_index):
        if col not in mine:
            continue
        h = STEP * max(1.0, abs(theta[col]))
        tp, tm = theta.copy(), theta.copy()
        tp[col] += h
        tm[col] -= h
        pr_p, b_p, _ = fn(tp, pose, poly, idx)
        pr_m, b_m, _ = fn(tm, pose, poly, idx)
        Jt_r[:, j] = (pr_p - pr_m) / (2 * h)
        Jt_b[:, j] = wrap(b_p - b_m) / (2 * h)
    Jv_r, Jv_b = np.zeros((n, 3)), np.zeros((n, 3))
    if velocity is not None:
        for c in range(3):
            vp, vm = velocity.copy(), velocity.copy()
            vp[:, c] += STEP
            vm[:, c] -= STEP
            pr_p, b_p, _ = fn(theta, pose, poly, idx, vp)
            pr_m, b_m, _ = fn(theta, pose, poly, idx, vm)
            Jv_r[:, c] = (pr_p - pr_m) / (2 * STEP)
            Jv_b[:, c] = wrap(b_p - b_m) / (2 * STEP)
    Jr = {"pose": Jp_r[r_idx], "poly": Jc[r_idx], "theta": Jt_r[r_idx] if len(ls_index) else None,
          "velocity": Jv_r[r_idx]}
    Jb = {"pose": Jp_b[b_idx], "poly": np.zeros((len(b_idx), len(poly))),
          "theta": Jt_b[b_idx] if len(ls_index) else None, "velocity": Jv_b[b_idx]}
    return (er, Jr), (eb, Jb)
