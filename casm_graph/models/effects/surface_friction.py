"""surface_friction: the floor slows the robot by different amounts in different places (a carpet, a rug, a ramp).

The slow-down is a field over the visited area: a bilinear surface through a grid of nodes, each
node's value the fraction of its speed the robot loses there. The field is linear in its node
values, so least squares finds a patch wherever it lies (a fixed split, say at x = 0, misses one
whose edges are elsewhere), and a Gaussian prior per node keeps the unvisited corners at zero.
A floor slower everywhere is a slower action model: the field's level and the action model's scale
are one quantity, so the field acts through its nodes' deviations from their mean (the action model
is the speed on the grid's average floor) and its level is left to the prior. The field is a family:
order 1 a plane (the floor slower toward one side: two slopes), order K >= 2 a K x K grid of nodes; the
diagnosis keeps the member BIC prefers.
"""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register

NODES = 4                 # nodes per axis of the field's richest form (the default)
PRIOR_SIGMA = 0.3         # prior std of each node's slow-down (a carpet rarely costs more than half the speed)
PAD = 0.05                # share of the visited span added on each side of the field
MIN_SPAN = 0.5            # m: the field spans at least this much along each axis


def extent_around(xy: np.ndarray) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1): the visited area (1st to 99th percentile of ``xy``), padded."""
    lo, hi = np.percentile(np.asarray(xy, float)[:, :2], [1.0, 99.0], axis=0)
    mid, half = (lo + hi) / 2, np.maximum((hi - lo) * (0.5 + PAD), MIN_SPAN / 2)
    return (float(mid[0] - half[0]), float(mid[1] - half[1]), float(mid[0] + half[0]), float(mid[1] + half[1]))


def bilinear(xy: np.ndarray, extent, nodes: int = NODES) -> np.ndarray:
    """(n, nodes**2) weights of each (x, y) on the grid's nodes (row-major from (x0, y0)); clamped at the edges."""
    x0, y0, x1, y1 = extent
    u = np.clip((xy[:, 0] - x0) / (x1 - x0), 0.0, 1.0) * (nodes - 1)
    w = np.clip((xy[:, 1] - y0) / (y1 - y0), 0.0, 1.0) * (nodes - 1)
    i, j = np.minimum(u.astype(int), nodes - 2), np.minimum(w.astype(int), nodes - 2)
    fu, fw = u - i, w - j
    out = np.zeros((len(xy), nodes * nodes))
    rows = np.arange(len(xy))
    for di, dj, wt in ((0, 0, (1 - fu) * (1 - fw)), (1, 0, fu * (1 - fw)), (0, 1, (1 - fu) * fw), (1, 1, fu * fw)):
        np.add.at(out, (rows, (j + dj) * nodes + i + di), wt)
    return out


@register
class SurfaceFriction(Effect):
    name = "surface_friction"
    channel = "motion"
    params = tuple(f"slow_{i}_{j}" for j in range(NODES) for i in range(NODES))   # node (i along x, j along y)
    start = (0.0,) * NODES ** 2
    scale = (0.02,) * NODES ** 2
    orders = (1, 2, 3, NODES)        # 1: a plane; K: nodes per axis
    order = NODES
    explains = tuple((ch, c) for ch in ("forward", "lateral", "turn") for c in ("place", "x", "y"))
    distinguished_by = ("the same actions run in every part of the field early and late: a slow floor slows the "
                        "robot where it is, a fading battery when it is")
    physics = ("The floor is not uniform: on part of the field (a carpet, a rug) the feet or wheels slip or drag, so "
               "every command covers a smaller fraction of its usual distance there; the slow-down is a smooth field "
               "over the visited area (a plane, or a grid of 2 x 2 to 4 x 4 nodes).")

    def __init__(self, log=None, extent=None, order=None):
        super().__init__(log, order)
        self.extent = None if extent is None else tuple(float(v) for v in extent)

    def set_order(self, order: int) -> None:
        super().set_order(order)
        self.params = (("tilt_east", "tilt_north") if order == 1 else
                       tuple(f"slow_{i}_{j}" for j in range(order) for i in range(order)))
        self.start, self.scale = (0.0,) * len(self.params), (0.02,) * len(self.params)

    def restore(self, entry: dict) -> None:
        super().restore(entry)
        if entry.get("order") is None and entry.get("grid") is not None:     # written before the family had orders
            self.set_order(int(entry["grid"][0]))
        if entry.get("extent") is not None:
            self.extent = tuple(float(v) for v in entry["extent"])

    def prior(self):
        return np.zeros(len(self.params)), np.full(len(self.params), PRIOR_SIGMA)

    def free_parameters(self) -> int:
        return len(self.params) - (self.order > 1)      # a grid's level belongs to the action model

    def slow(self, theta: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Fraction of its speed the robot loses at each (x, y), against the field's average floor (a plane's
        slopes are the east and north edges against the west and south ones)."""
        theta, xy = np.asarray(theta, float), np.atleast_2d(xy)
        if self.order == 1:
            x0, y0, x1, y1 = self.extent
            u = np.clip((xy[:, 0] - x0) / (x1 - x0), 0.0, 1.0) - 0.5
            w = np.clip((xy[:, 1] - y0) / (y1 - y0), 0.0, 1.0) - 0.5
            return theta[0] * u + theta[1] * w
        return bilinear(xy, self.extent, self.order) @ (theta - theta.mean())

    def velocity(self, theta, v, ctx):
        if self.extent is None:              # the first poses the fit hands over fix the field's extent
            self.extent = extent_around(ctx["pose"])
        return v * (1.0 - self.slow(theta, ctx["pose"][:, :2]))[:, None]

    def describe(self, theta):
        theta = np.asarray(theta, float)
        extent = {"extent": None if self.extent is None else list(self.extent)}
        if self.order == 1:
            return {**super().describe(theta), **extent}
        return {**super().describe(theta - theta.mean()), "grid": [self.order, self.order], **extent}

    def simulate_params(self, value, rng):
        """The nodes east of x = 0 (of a field centred on the origin) slower than those west of it by ``value``
        (on an odd grid the middle column half as slow; a plane's east edge ``value`` slower than its west)."""
        if self.order == 1:
            return np.array([float(value), 0.0])
        i = np.arange(len(self.params)) % self.order
        return float(value) * np.clip(i - (self.order - 1) / 2 + 0.5, 0.0, 1.0)
