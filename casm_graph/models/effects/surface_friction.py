"""surface_friction: the floor slows the robot by different amounts in different places (a carpet, a rug, a ramp).

The slow-down is a field over the visited area: a bilinear surface through a grid of nodes, each
node's value the fraction of its speed the robot loses there. The field is linear in its node
values, so least squares finds a patch wherever it lies (a fixed split, say at x = 0, misses one
whose edges are elsewhere), and a Gaussian prior per node keeps the unvisited corners at zero.
A floor slower everywhere is a slower action model: the field's level and the action model's scale
are one quantity, so a grid acts through its deviations from its average over the steps the robot ran (the
action model is the speed on the average floor it crossed; ``visits``, each node's share of the steps, fixed when
the field is placed) and its level is left to the prior. Against the mean of the nodes instead, nodes the robot
never reached could carry the level: the visited floor 88 % slower, three empty corners five times faster and
the command map eight times faster, one omnidirectional world's calibration with the grid added. The field is a family:
order 0 a rectangular patch (a rug) whose slow-down and four edges are the parameters, order 1 a plane (the
floor slower toward one side: two slopes), order K >= 2 a K x K grid of nodes; the diagnosis keeps the member
BIC prefers. A grid smears a patch's sharp edges over a cell (the 4 x 4 one over a third of the field, which
leaves residual structure along x or y once added); the patch has them, in five parameters. Its edges start
where the poses of a fit without it show the robot covering least of its commanded distance (:meth:`begin`).
Turning and driving need not lose alike (feet that drag on a rug pivot more easily than they stride): every member
ends with ``turn_share``, the share of the field's slow-down the turn rate feels (1: all alike).
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit

from casm_graph.models.effects.base import Effect, register

NODES = 4                 # nodes per axis of the default form, the family's richest
PATCH = 0                 # the order of the rectangular patch
CELLS = 12                # cells per axis of the grid a patch's start is searched on
EDGE = 1 / 48             # a patch edge's width (logistic), as a share of the field's span
MIN_SHARE = 0.03          # a patch's start covers at least this share of the commanded distance, and leaves as much
GROUPS = 64               # steps asking for one of at most this many velocities are compared within their velocity
SPEED_BINS = 8            # else within these quantile bins of commanded speed
PRIOR_SIGMA = 0.3         # prior std of each node's slow-down (a carpet rarely costs more than half the speed)
SHARE_SIGMA = 0.5         # prior std of the turn share around 1 (turns slowed as much as driving)
FASTEST = 3.0             # one part of a floor lets the robot run at most this many times as fast as another
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


def shape(order: int) -> tuple[tuple, tuple, tuple]:
    """(params, start, scale) of the member of ``order``: its field's parameters (a patch's slow-down and edges, a
    plane's two slopes, or a grid's nodes, i along x and j along y), then the turn share."""
    if order == PATCH:
        field, start, scale = ("slow", "west", "east", "south", "north"), (0.0,) * 5, (0.02, 0.1, 0.1, 0.1, 0.1)
    else:
        field = (("tilt_east", "tilt_north") if order == 1 else
                 tuple(f"slow_{i}_{j}" for j in range(order) for i in range(order)))
        start, scale = (0.0,) * len(field), (0.02,) * len(field)
    return (*field, "turn_share"), (*start, 1.0), (*scale, 0.1)


@register
class SurfaceFriction(Effect):
    name = "surface_friction"
    channel = "motion"
    map_bound = True
    params, start, scale = shape(NODES)
    orders = (PATCH, 1, 2, 3, NODES)    # 0: a patch; 1: a plane; K: nodes per axis
    order = NODES
    explains = tuple((ch, c) for ch in ("forward", "lateral", "turn") for c in ("place", "x", "y"))
    signature = "field"
    distinguished_by = ("the same actions run in every part of the field early and late: a slow floor slows the "
                        "robot where it is, a fading battery when it is")
    physics = ("The floor is not uniform: on part of the field (a carpet, a rug) the feet or wheels slip or drag, so "
               "every command covers a smaller fraction of its usual distance there; the slow-down is a smooth field "
               "over the visited area (a rectangular patch, a plane, or a grid of 2 x 2 to 4 x 4 nodes), the turn "
               "rate losing its own share of it.")

    def __init__(self, log=None, extent=None, order=None):
        super().__init__(log, order)
        self.extent = None if extent is None else tuple(float(v) for v in extent)
        self.visits = None        # a grid's node weights averaged over the steps: where its level is measured

    def set_order(self, order: int) -> None:
        super().set_order(order)
        self.params, self.start, self.scale = shape(order)

    def begin(self, model, poses: np.ndarray) -> None:
        """The field's extent from the poses (T+1, 3) of a fit without it, and a patch's start: on a grid of ``CELLS``
        x ``CELLS`` cells, the rectangle of cells inside which the steps covered a different share of their commanded
        distance than outside (the largest between-group sum of squares of the shortfall along each step's commanded
        direction)."""
        poses = np.asarray(poses, float)
        if self.extent is None:
            self.extent = extent_around(poses)
        self.place(poses)
        if self.order != PATCH or self.log is None or len(poses) != self.log.steps + 1:
            return
        start = patch_start(poses, model.step_velocities(self.log) * self.log.dt[:, None], self.extent)
        if start is not None:
            self.start = (*start, 1.0)

    def place(self, poses: np.ndarray) -> None:
        """A grid's ``visits`` from the poses (T+1, 3) of a fit without it (once: the level they define stays put;
        a field placed otherwise, as the simulator's, keeps the nodes' mean as its level)."""
        if self.visits is None and self.order > 1 and self.extent is not None:
            self.visits = bilinear(np.asarray(poses, float)[:, :2], self.extent, self.order).mean(axis=0)

    def restore(self, entry: dict) -> None:
        super().restore(entry)
        if entry.get("order") is None and entry.get("grid") is not None:     # written before the family had orders
            self.set_order(int(entry["grid"][0]))
        if entry.get("extent") is not None:
            self.extent = tuple(float(v) for v in entry["extent"])
        if entry.get("visits") is not None:
            self.visits = np.asarray(entry["visits"], float)

    def prior(self):
        if self.order == PATCH:           # an edge beyond the visited area drifts to its border
            x0, y0, x1, y1 = self.extent if self.extent is not None else (-50.0, -50.0, 50.0, 50.0)
            return (np.array([0.0, x0, x1, y0, y1, 1.0]),
                    np.array([PRIOR_SIGMA, x1 - x0, x1 - x0, y1 - y0, y1 - y0, SHARE_SIGMA]))
        n = len(self.params) - 1
        return np.append(np.zeros(n), 1.0), np.append(np.full(n, PRIOR_SIGMA), SHARE_SIGMA)

    def free_parameters(self) -> int:
        return len(self.params) - (self.order > 1)      # a grid's level belongs to the action model

    def slow(self, theta: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Fraction of its speed the robot loses at each (x, y), against the field's average floor (a plane's
        slopes are the east and north edges against the west and south ones; a patch's against the floor off it);
        ``theta`` the member's parameters, the turn share last."""
        theta, xy = np.asarray(theta, float)[:-1], np.atleast_2d(xy)
        if self.order == PATCH:
            return theta[0] * inside(xy, theta[1:], self.extent)
        if self.order == 1:
            x0, y0, x1, y1 = self.extent
            u = np.clip((xy[:, 0] - x0) / (x1 - x0), 0.0, 1.0) - 0.5
            w = np.clip((xy[:, 1] - y0) / (y1 - y0), 0.0, 1.0) - 0.5
            return theta[0] * u + theta[1] * w
        return bilinear(xy, self.extent, self.order) @ self.relative(theta)

    def implausible(self, theta):
        """A floor lets the robot run at most ``FASTEST`` times as fast over one part as over another, driving or
        turning: a fit that says more bends the floor around something else (a window glare hidden from the model
        can be fitted as a 0.6-m strip where the robot runs 4.5 times as fast as elsewhere)."""
        theta = np.asarray(theta, float)
        field, share = theta[:-1], float(theta[-1])
        if self.order == PATCH:
            slows = field[:1]
        elif self.order == 1:
            half = 0.5 * (abs(field[0]) + abs(field[1]))
            slows = np.array([-half, half])
        else:                                 # the nodes the robot reached (a bilinear field's extremes)
            seen = np.ones(len(field), bool) if self.visits is None else self.visits > 0.1 / len(field)
            slows = self.relative(field)[seen]
        for what, k in (("drive", 1.0), ("turn", share)):
            speed = np.append(1.0 - k * slows, 1.0)          # 1: the floor the slow-down is measured against
            if speed.min() <= 0.0:
                return f"the floor would stop the robot's {what} over part of the field (or reverse it)"
            if speed.max() / speed.min() > FASTEST:
                return (f"the floor would let the robot {what} {speed.max() / speed.min():.1f} times as fast over one "
                        f"part of the field as over another (a floor changes it at most {FASTEST:g} times)")
        return None

    def relative(self, nodes: np.ndarray) -> np.ndarray:
        """A grid's node values against its level: the average over the visited steps (``visits``), or the nodes'
        mean for a model written before it was recorded."""
        level = nodes.mean() if self.visits is None else float(self.visits @ nodes)
        return nodes - level

    def velocity(self, theta, v, ctx):
        if self.extent is None:              # the first poses the fit hands over fix the field's extent
            self.extent = extent_around(ctx["pose"])
        slow = self.slow(theta, ctx["pose"][:, :2])[:, None]
        return v * (1.0 - slow * np.array([1.0, 1.0, float(theta[-1])]))

    def describe(self, theta):
        theta = np.asarray(theta, float)
        extent = {"extent": None if self.extent is None else list(self.extent)}
        if self.order in (PATCH, 1):
            return {**super().describe(theta), **extent}
        visits = {} if self.visits is None else {"visits": [float(v) for v in self.visits]}
        shown = np.append(self.relative(theta[:-1]), theta[-1])
        return {**super().describe(shown), "grid": [self.order, self.order], **extent, **visits}

    def simulate_params(self, value, rng):
        """The nodes east of x = 0 (of a field centred on the origin) slower than those west of it by ``value``
        (on an odd grid the middle column half as slow; a plane's east edge ``value`` slower than its west), turns
        slowed alike."""
        if self.order == 1:
            return np.array([float(value), 0.0, 1.0])
        if self.order == PATCH:              # the east half, its other edges beyond the field
            x0, y0, x1, y1 = self.extent
            return np.array([float(value), (x0 + x1) / 2, 2 * x1 - x0, 2 * y0 - y1, 2 * y1 - y0, 1.0])
        i = np.arange(len(self.params) - 1) % self.order
        return np.append(float(value) * np.clip(i - (self.order - 1) / 2 + 0.5, 0.0, 1.0), 1.0)


def inside(xy: np.ndarray, edges, extent) -> np.ndarray:
    """How far each (x, y) lies inside the rectangle (west, east, south, north): 1 well inside, 0 well outside,
    logistic across each edge over ``EDGE`` of the field's span."""
    w, e, s, n = (float(v) for v in edges)
    x0, y0, x1, y1 = extent
    kx, ky = EDGE * (x1 - x0), EDGE * (y1 - y0)
    return (expit((xy[:, 0] - w) / kx) * expit((e - xy[:, 0]) / kx) * expit((xy[:, 1] - s) / ky)
            * expit((n - xy[:, 1]) / ky))


def patch_start(poses: np.ndarray, commanded: np.ndarray, extent) -> tuple | None:
    """(slow, west, east, south, north) of the rectangle of grid cells inside which the steps fell short of their
    commanded displacement (``commanded``: (T, 3), each step's body displacement under the model) by a different
    share than outside, the steps that asked for the same velocity compared among themselves (an action model fitted
    without the patch gives an action run mostly on it the patch's speed); None when the steps barely move."""
    d = np.diff(poses[:, :2], axis=0)
    h = poses[:-1, 2] + 0.5 * np.diff(np.unwrap(poses[:, 2]))
    c, s = np.cos(h), np.sin(h)
    body = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    length = np.hypot(commanded[:, 0], commanded[:, 1])
    ok = length > 1e-9
    if ok.sum() < 10:
        return None
    unit = commanded[ok, :2] / length[ok, None]
    x = length[ok]
    # m each step fell short of (negative) or ran past its command; a jump or a spin says nothing of the floor
    y = np.clip(np.sum((body[ok] - commanded[ok, :2]) * unit, axis=1), -x, x)
    _, group = np.unique(np.round(commanded[ok], 9), axis=0, return_inverse=True)
    if group.max() >= GROUPS:                                         # continuous commands: bins of speed
        group = np.searchsorted(np.quantile(x, np.linspace(0, 1, SPEED_BINS + 1)[1:-1]), x)
    group = np.unique(group.ravel(), return_inverse=True)[1].ravel()   # tied quantiles leave no bin empty
    G = int(group.max()) + 1
    xa = np.bincount(group, x * x, G)
    y = y - x * (np.bincount(group, x * y, G) / xa)[group]            # each group's own mean shortfall removed
    mid = 0.5 * (poses[:-1, :2] + poses[1:, :2])[ok]
    x0, y0, x1, y1 = extent
    i = np.clip(((mid[:, 0] - x0) / (x1 - x0) * CELLS).astype(int), 0, CELLS - 1)
    j = np.clip(((mid[:, 1] - y0) / (y1 - y0) * CELLS).astype(int), 0, CELLS - 1)
    sxy, sxx = np.zeros((CELLS + 1, CELLS + 1)), np.zeros((G, CELLS + 1, CELLS + 1))
    np.add.at(sxy, (i + 1, j + 1), x * y)
    np.add.at(sxx, (group, i + 1, j + 1), x * x)
    pxy, pxx = sxy.cumsum(0).cumsum(1), sxx.cumsum(1).cumsum(2)
    lo, hi = np.triu_indices(CELLS)                 # cell ranges [lo, hi] along one axis
    a, b, u, v = lo[:, None], hi[:, None] + 1, lo[None, :], hi[None, :] + 1
    S = pxy[b, v] - pxy[a, v] - pxy[b, u] + pxy[a, u]
    Xg = pxx[:, b, v] - pxx[:, a, v] - pxx[:, b, u] + pxx[:, a, u]      # per group, inside each rectangle
    X = Xg.sum(0)
    info = X - np.sum(Xg ** 2 / xa[:, None, None], axis=0)            # the indicator's variance left within groups
    fair = (X > MIN_SHARE * xa.sum()) & (X < (1 - MIN_SHARE) * xa.sum()) & (info > MIN_SHARE * X)
    if not fair.any():
        return None
    score = np.where(fair, S ** 2 / np.where(fair, info, 1.0), -1.0)
    k, m = np.unravel_index(np.argmax(score), score.shape)
    cx, cy = (x1 - x0) / CELLS, (y1 - y0) / CELLS
    return (float(-S[k, m] / info[k, m]), x0 + lo[k] * cx, x0 + (hi[k] + 1) * cx, y0 + lo[m] * cy,
            y0 + (hi[m] + 1) * cy)
