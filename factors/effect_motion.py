"""Effect-augmented action factor: the action factor on the velocity a step really runs under the motion effects.

The effects' velocity hooks are plain forward physics; their derivatives with respect to the
table rows (own and previous action), the start pose and the effect parameters are central
differences of the vectorised hook (few parameters, one numpy pass each), chained into the
analytic Jacobians of :mod:`factors.action`. tests/test_effects.py checks the chain numerically.
"""
from __future__ import annotations

import numpy as np

from . import action

STEP = 1e-6


def velocity(fn, v_own, v_prev, pose):
    return fn(v_own, v_prev, pose)


def body_step(pose, c, h):
    """``pose`` moved by ``h`` along body-frame tangent axis ``c`` (Pose2 retract to first order)."""
    p = pose.copy()
    cth, sth = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    if c == 0:
        p[:, 0] += h * cth
        p[:, 1] += h * sth
    elif c == 1:
        p[:, 0] -= h * sth
        p[:, 1] += h * cth
    else:
        p[:, 2] += h
    return p


def velocity_jacobians(fn, v_own, v_prev, pose, theta, columns):
    """Derivatives (n, 3, 3) of the effective velocity w.r.t. own row, previous row and pose, and (n, 3, m) w.r.t. ``theta[columns]``."""
    out = {}
    for name in ("own", "prev", "pose"):
        J = np.empty((len(v_own), 3, 3))
        for c in range(3):
            args = []
            for sign in (1.0, -1.0):
                a = [v_own.copy(), v_prev.copy(), pose]
                if name == "pose":
                    a[2] = body_step(pose, c, sign * STEP)
                else:
                    a[0 if name == "own" else 1][:, c] += sign * STEP
                args.append(fn(*a))
            J[:, :, c] = (args[0] - args[1]) / (2 * STEP)
        out[name] = J
    Jt = np.zeros((len(v_own), 3, len(columns)))
    for j, col in enumerate(columns):
        tp, tm = theta.copy(), theta.copy()
        h = STEP * max(1.0, abs(theta[col]))
        tp[col] += h
        tm[col] -= h
        Jt[:, :, j] = (fn(v_own, v_prev, pose, tp) - fn(v_own, v_prev, pose, tm)) / (2 * h)
    out["theta"] = Jt
    return out


def error(fn, P, V, seg_row, prev_row, dt, theta, ls_index, motion_slices):
    """Action-factor residual with effects; returns (e, [Ha, Hb, Hv], chained derivatives)."""
    v_own, v_prev, pose = V[seg_row], V[prev_row], P[:-1]
    v = fn(v_own, v_prev, pose)
    e, (Ha, Hb, Hvn) = action.error(P[:-1], P[1:], v, np.ones(len(v)), dt)
    n = len(v)
    if not motion_slices:
        dv = {"own": Hvn, "prev": np.zeros((n, 3, 3)), "pose": np.zeros((n, 3, 3)), "theta": None}
        return e, [Ha, Hb, Hvn], dv
    mine = np.concatenate([np.arange(s.start, s.stop) for s in motion_slices]).astype(int)
    cols = [j for j, c in enumerate(ls_index) if c in set(mine.tolist())]
    J = velocity_jacobians(fn, v_own, v_prev, pose, theta, [int(ls_index[j]) for j in cols])
    Jt = np.zeros((n, 3, len(ls_index)))
    for k, j in enumerate(cols):
        Jt[:, :, j] = J["theta"][:, :, k]
    chain = {k: np.einsum("nij,njk->nik", Hvn, J[k]) for k in ("own", "prev", "pose")}
    chain["theta"] = np.einsum("nij,njk->nik", Hvn, Jt)
    return e, [Ha, Hb, Hvn], chain
