"""Command-model factor: the displacement between two poses equals the commands integrated through f.

Between two poses the robot ran k command steps; step j moves it forward by f_v(c_j) dt_j along
the heading it had at the step's start (``lead`` 0, the paper's step) or at its middle (``lead`` 0.5: the
chord of the arc a command held over the step drives, exact to second order), sideways by f_y(c_j) dt_j (an
omnidirectional robot's ``vy`` map; none for ``v, w``) and turns it by f_w(c_j) dt_j. With f_v = Bv a,
f_y = By c and f_w = Bw b linear in the parameters ``p = [a, c, b]``, the predicted displacement and its derivative are sums
over the steps; segments are padded to a common length with dt = 0.
"""
from __future__ import annotations

import numpy as np

from .base import register, relative, wrap


def displacement(p: np.ndarray, Bv: np.ndarray, Bw: np.ndarray, dt: np.ndarray, By: np.ndarray | None = None,
                 lead: float = 0.0):
    """Predicted (dx, dy, dtheta) in the start frame, and its (n, 3, P) derivative w.r.t. ``p``.

    ``Bv`` (n, k, nv), ``Bw`` (n, k, nw) and ``By`` (n, k, ny; None: no sideways map) are the basis rows of
    each step, ``dt`` (n, k) the step lengths (0 for padding), ``p`` (n, nv + ny + nw) or (nv + ny + nw,);
    ``lead`` the share of a step's turn made before it moves (0: along its start heading, 0.5: its middle).
    """
    nv, ny = Bv.shape[-1], (0 if By is None else By.shape[-1])
    p = np.broadcast_to(np.asarray(p, float), (Bv.shape[0], nv + ny + Bw.shape[-1]))
    v = np.einsum("nki,ni->nk", Bv, p[:, :nv])
    w = np.einsum("nki,ni->nk", Bw, p[:, nv + ny:])
    turn = w * dt
    phi = np.cumsum(turn, axis=1) - (1.0 - lead) * turn   # heading each step moves along
    Phi = np.cumsum(Bw * dt[..., None], axis=1) - (1.0 - lead) * Bw * dt[..., None]   # d phi / d b
    c, s = np.cos(phi), np.sin(phi)
    vdt = v * dt
    J = np.zeros((Bv.shape[0], 3, p.shape[1]))
    J[:, 0, :nv] = np.einsum("nk,nki->ni", c * dt, Bv)
    J[:, 1, :nv] = np.einsum("nk,nki->ni", s * dt, Bv)
    J[:, 2, nv + ny:] = np.einsum("nk,nki->ni", dt, Bw)
    if not ny:
        d = np.stack([np.sum(c * vdt, 1), np.sum(s * vdt, 1), np.sum(turn, 1)], axis=1)
        J[:, 0, nv:] = -np.einsum("nk,nki->ni", s * vdt, Phi)
        J[:, 1, nv:] = np.einsum("nk,nki->ni", c * vdt, Phi)
        return d, J
    udt = np.einsum("nki,ni->nk", By, p[:, nv:nv + ny]) * dt
    d = np.stack([np.sum(c * vdt - s * udt, 1), np.sum(s * vdt + c * udt, 1), np.sum(turn, 1)], axis=1)
    J[:, 0, nv:nv + ny] = -np.einsum("nk,nki->ni", s * dt, By)
    J[:, 1, nv:nv + ny] = np.einsum("nk,nki->ni", c * dt, By)
    J[:, 0, nv + ny:] = -np.einsum("nk,nki->ni", s * vdt + c * udt, Phi)
    J[:, 1, nv + ny:] = np.einsum("nk,nki->ni", c * vdt - s * udt, Phi)
    return d, J


def turned(d: np.ndarray, lead: float) -> np.ndarray:
    """(n, 3) steps' displacements ``d`` (velocity times time, body frame) moved along the heading ``lead`` of their
    own turn on: each step's displacement in its start frame (``-lead`` takes it back)."""
    d = np.asarray(d, float)
    if not lead:
        return d
    z = np.exp(1j * lead * d[:, 2]) * (d[:, 0] + 1j * d[:, 1])
    return np.column_stack([z.real, z.imag, d[:, 2]])


def integrate(v: np.ndarray, dt: np.ndarray, lead: float = 0.0) -> np.ndarray:
    """(n, 3) displacement in the start frame of steps with body velocities ``v`` (n, k, 3), each step along
    the heading ``lead`` of its turn on (as :func:`displacement`; lateral velocity allowed), and the (n, k, 3)
    pose of every step's start in that frame."""
    turn = v[..., 2] * dt
    phi = np.cumsum(turn, axis=1) - turn
    along = phi + lead * turn
    c, s = np.cos(along), np.sin(along)
    dx = (c * v[..., 0] - s * v[..., 1]) * dt
    dy = (s * v[..., 0] + c * v[..., 1]) * dt
    x, y = np.cumsum(dx, axis=1), np.cumsum(dy, axis=1)
    starts = np.stack([x - dx, y - dy, phi], axis=-1)
    return np.column_stack([x[:, -1], y[:, -1], phi[:, -1] + turn[:, -1]]), starts


@register("command", ("pose", "pose", "vector"))
def error(a: np.ndarray, b: np.ndarray, p: np.ndarray, Bv: np.ndarray, Bw: np.ndarray, dt: np.ndarray,
          By: np.ndarray | None = None, lead: float = 0.0):
    """Body-frame displacement from pose a to pose b minus the commands integrated through f (``lead``: as
    :func:`displacement`)."""
    if Bv.ndim == 2:                     # one segment bound into a CustomFactor
        Bv, Bw, dt = Bv[None], Bw[None], dt[None]
        By = None if By is None else By[None]
    if By is not None and not By.shape[-1]:
        By = None
    rel, Ha, Hb = relative(a, b)
    pred, Jp = displacement(p, Bv, Bw, dt, By, lead)
    e = np.column_stack([rel[:, 0] - pred[:, 0], rel[:, 1] - pred[:, 1], wrap(rel[:, 2] - pred[:, 2])])
    return e, [Ha, Hb, -Jp]
