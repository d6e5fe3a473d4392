"""SCASM (Stronger & Stone): online calibration of a 1-D action and sensor model from each other.

The robot walks toward and away from one beacon. The sensor model S maps a reading to a location,
the action model A maps a command to a velocity; neither has units of its own, so both are learned
up to scale and offset and evaluated after the best fit to the true models (PAPERS.md section 2).

``online`` is the paper's algorithm (its Fig. 4): incremental discounted regressions kept as O(1)
sums, gamma = 0.999, lambda = 1/30, t_start = 20 s, A0(c) = c. ``graph_online`` calibrates the same
log as a 1-D factor graph (a location per frame, one coefficient vector per model) with
``gtsam.ISAM2``, also frame by frame; the problem is linear, so every ISAM2 update is exact.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from casm_graph.io.log import Log, LogError

GAMMA = 0.999
LAMBDA = 1.0 / 30.0
T_START = 20.0
ACTION_DEGREE = 4
SENSOR_DEGREE = 3


# ----------------------------------------------------------------------------- the log
@dataclass(frozen=True)
class Walk:
    """A 1-D log: command per frame, readings at frames; ``x_true`` only for plots."""

    dt: np.ndarray              # (T,) duration of each command step
    command: np.ndarray         # (T,) the one-dimensional command
    obs_step: np.ndarray        # (N,) pose index of each reading
    reading: np.ndarray         # (N,)
    t: np.ndarray               # (T+1,) pose times


def walk_of(log: Log) -> Walk:
    """The 1-D view of a log, or LogError if it has more than one landmark or a 2-D command."""
    if len(log.landmark_ids) != 1:
        raise LogError(f"landmarks.csv: SCASM needs exactly one landmark (found {len(log.landmark_ids)})")
    if log.controls is None:
        raise LogError("commands.csv: SCASM needs a continuous one-dimensional command ('v' with 'w' = 0)")
    names = log.control_names
    c = log.controls
    other = [j for j, n in enumerate(names) if n != names[0]]
    if np.any(c[:, other] != 0):
        j = other[int(np.flatnonzero(np.any(c[:, other] != 0, axis=0))[0])]
        i = int(np.flatnonzero(c[:, j] != 0)[0])
        raise LogError(f"commands.csv, row {log.file_row(i)}, column '{names[j]}': SCASM needs a one-dimensional "
                       f"command, so '{names[j]}' must be 0 throughout")
    ok = np.isfinite(log.obs_reading)
    if ok.sum() < 10:
        raise LogError("observations.csv: SCASM needs readings (column 'reading'); fewer than 10 found")
    return Walk(dt=log.dt, command=c[:, 0], obs_step=log.obs_step[ok], reading=log.obs_reading[ok],
                t=log.pose_times)


# ----------------------------------------------------------------------------- the paper's algorithm
class DiscountedRegression:
    """Weighted least squares y ~ alpha + V @ beta from O(1) running sums (paper eqs. 5 and 6).

    Each new point enters with weight 1 and every earlier weight is multiplied by ``gamma``.
    """

    def __init__(self, dim: int, gamma: float = GAMMA):
        self.gamma = gamma
        self.n = 0.0
        self.sv = np.zeros(dim)
        self.svv = np.zeros((dim, dim))
        self.sy = 0.0
        self.svy = np.zeros(dim)
        self.count = 0

    def add(self, v: np.ndarray, y: float) -> None:
        g = self.gamma
        self.n = g * self.n + 1.0
        self.sv = g * self.sv + v
        self.svv = g * self.svv + np.outer(v, v)
        self.sy = g * self.sy + y
        self.svy = g * self.svy + v * y
        self.count += 1

    def solve(self) -> tuple[float, np.ndarray]:
        """(alpha, beta); the minimum-norm beta when the centred sums are singular (e.g. one command so far)."""
        mm = self.svv - np.outer(self.sv, self.sv) / self.n
        my = self.svy - self.sv * self.sy / self.n
        beta = np.linalg.lstsq(mm, my, rcond=1e-12)[0]
        return (self.sy - self.sv @ beta) / self.n, beta


@dataclass
class PolyModel:
    """f(x) = sum coef[i] * (x / scale)**i: the learned S or A (scale only conditions the sums)."""

    coef: np.ndarray
    scale: float

    def __call__(self, x) -> np.ndarray:
        return np.polynomial.polynomial.polyval(np.asarray(x, float) / self.scale, self.coef)

    def to_json(self) -> dict:
        return {"coefficients": [float(c) for c in self.coef], "scale": float(self.scale),
                "form": "sum coefficients[i] * (x / scale)**i"}


@dataclass
class OnlineResult:
    """The learned models at the end, the two location estimates per frame, and a history."""

    action: PolyModel
    sensor: PolyModel
    x_a: np.ndarray                     # (T+1,) dead-reckoned location (pulled toward x_s)
    x_s: np.ndarray                     # (N,) sensor location of each reading (NaN before t_start)
    history: list = field(default_factory=list)   # (t, action coef, sensor coef) every second
    seconds: float = 0.0


def online(walk: Walk, gamma: float = GAMMA, lam: float = LAMBDA, t_start: float = T_START,
           action_degree: int = ACTION_DEGREE, sensor_degree: int = SENSOR_DEGREE,
           command_scale: float | None = None, every: float = 1.0) -> OnlineResult:
    """The paper's Fig. 4, frame by frame.

    x_a is dead reckoning with A0(c) = c until 2 t_start and with the learned A after; from t_start
    each reading gives x_s = S(obs), adds (integrals of c^i, x_s) to A's regression and pulls x_a
    toward x_s by lambda; every reading adds (obs, x_a) to S's regression.
    """
    t0 = time.perf_counter()
    c_scale = command_scale or float(np.max(np.abs(walk.command))) or 1.0
    o_scale = float(walk.reading[0])
    T = len(walk.command)
    u = walk.command / c_scale
    powers_a = np.arange(action_degree + 1)
    powers_s = np.arange(1, sensor_degree + 1)
    reg_a = DiscountedRegression(action_degree + 1, gamma)
    reg_s = DiscountedRegression(sensor_degree, gamma)
    a_coef = np.zeros(action_degree + 1)
    a_coef[1] = c_scale                                    # A0(c) = c
    s_alpha, s_beta = 0.0, np.zeros(sensor_degree)
    a0 = a_coef.copy()
    integ = np.zeros(action_degree + 1)                   # int_0^t u(s)^i ds
    x_a = np.empty(T + 1)
    x_s = np.full(len(walk.reading), np.nan)
    xa = 0.0
    hist = []
    next_hist = 0.0
    starts = np.searchsorted(walk.obs_step, np.arange(T + 2))
    for k in range(T + 1):
        t = walk.t[k]
        for i in range(starts[k], starts[k + 1]):
            obs = walk.reading[i]
            if t > t_start:
                xs = s_alpha + (obs / o_scale) ** powers_s @ s_beta
                x_s[i] = xs
                reg_a.add(integ.copy(), xs)
                if t >= 2 * t_start:
                    _, beta = reg_a.solve()
                    a_coef = beta
                xa = (1 - lam) * xa + lam * xs
            reg_s.add((obs / o_scale) ** powers_s, xa)
            s_alpha, s_beta = reg_s.solve()
        x_a[k] = xa
        if t >= next_hist:
            hist.append((float(t), a_coef.copy(), np.concatenate([[s_alpha], s_beta])))
            next_hist += every
        if k < T:
            model = a0 if t < 2 * t_start else a_coef
            uk = u[k] ** powers_a
            xa += float(uk @ model) * walk.dt[k]
            integ += uk * walk.dt[k]
    return OnlineResult(action=PolyModel(a_coef.copy(), c_scale),
                        sensor=PolyModel(np.concatenate([[s_alpha], s_beta]), o_scale),
                        x_a=x_a, x_s=x_s, history=hist, seconds=time.perf_counter() - t0)


# ----------------------------------------------------------------------------- the paper's evaluation
@dataclass(frozen=True)
class Score:
    """Errors after the paper's best fits: action (mm/s, scale only), sensor (mm, scale and offset)."""

    action_rms: float
    sensor_rms: float
    action_scale: float         # true mm/s per learned unit/s
    sensor_scale: float         # true mm per learned unit
    ratio: float                # action_scale / sensor_scale; |ratio| = 1 when the models agree

    @property
    def consistency(self) -> float:
        """The paper's scale-consistency figure: | |ratio| - 1 |."""
        return abs(abs(self.ratio) - 1.0)


def score(action, sensor, truth: dict) -> Score:
    """Score learned ``action(c)`` and ``sensor(reading)`` against the true tables in truth_model.json.

    As the paper: the action model is multiplied by the scale that minimises the squared error to
    the true velocities at commands -300, -280, ..., 300; the sensor model gets the best a + b S
    against the true distances 1.2, 1.4, ..., 3.6 m at their noise-free readings.
    """
    am, sm = truth["action_model"], truth["sensor_model"]
    c = np.asarray(am["commands"])
    v = 1000.0 * np.asarray(am["velocities"])
    a = np.asarray(action(c), float)
    s_a = float(a @ v / (a @ a)) if a @ a > 0 else 0.0
    d = 1000.0 * np.asarray(sm["distances"])
    s = np.asarray(sensor(np.asarray(sm["readings"])), float)
    (off, s_s), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(s), s]), d, rcond=None)
    return Score(action_rms=float(np.sqrt(np.mean((s_a * a - v) ** 2))),
                 sensor_rms=float(np.sqrt(np.mean((off + s_s * s - d) ** 2))),
                 action_scale=s_a, sensor_scale=float(s_s), ratio=float(s_a / s_s) if s_s else float("nan"))


# ----------------------------------------------------------------------------- the factor graph, online
@dataclass
class GraphResult:
    """The graph's models, its location per frame, and the models after every ``every`` seconds."""

    action: PolyModel
    sensor: PolyModel
    x: np.ndarray
    action_std: np.ndarray
    sensor_std: np.ndarray
    motion_sigma: float
    sensor_sigma: float
    history: list = field(default_factory=list)
    seconds: float = 0.0
    updates: int = 0


KA, KS = gtsam.symbol("a", 0), gtsam.symbol("s", 0)


def _x(k: int) -> int:
    return gtsam.symbol("x", k)


class Graph1D:
    """The 1-D problem as linear factors, frame by frame.

    Motion x_{k+1} - x_k - dt A(c_k) (std ``sigma_m`` per frame), sensor x_k - S(obs) (std
    ``sigma_s``), A and S as two coefficient vectors. The gauge (offset and scale) is fixed by
    x_0 = 0 and by A's least-squares scale against A0(c) = c being 1, so locations come out in
    SCASM's units (command units times seconds); weak priors A = A0 and S = 0 keep the first frames
    solvable and are negligible after a few seconds.
    """

    def __init__(self, walk: Walk, action_degree: int = ACTION_DEGREE, sensor_degree: int = SENSOR_DEGREE,
                 command_scale: float | None = None):
        self.walk = walk
        self.c_scale = command_scale or float(np.max(np.abs(walk.command))) or 1.0
        self.o_scale = float(walk.reading[0])
        self.na, self.ns = action_degree + 1, sensor_degree + 1
        self.basis_a = (walk.command / self.c_scale)[:, None] ** np.arange(self.na)
        self.basis_s = (walk.reading / self.o_scale)[:, None] ** np.arange(self.ns)
        self.starts = np.searchsorted(walk.obs_step, np.arange(len(walk.command) + 2))
        self.a0 = np.zeros(self.na)
        self.a0[1] = self.c_scale

    def priors(self) -> list:
        """(blocks, b, sigma) of the gauge and the weak start priors."""
        g = np.linspace(-1, 1, 31)
        gauge = (g[:, None] ** np.arange(self.na) * g[:, None]).sum(0) / (g @ g) / self.c_scale
        return [([(_x(0), [[1.0]])], 0.0, 1e-3), ([(KA, gauge[None])], 1.0, 1e-4),
                ([(KA, np.eye(self.na))], self.a0, 10.0 * self.c_scale),
                ([(KS, np.eye(self.ns))], np.zeros(self.ns), 1e3)]

    def sensor(self, k: int, sigma_s: float) -> list:
        return [([(_x(k), [[1.0]]), (KS, -self.basis_s[i][None])], 0.0, sigma_s)
                for i in range(self.starts[k], self.starts[k + 1])]

    def motion(self, k: int, sigma_m: float) -> tuple:
        dt = self.walk.dt[k]
        return ([(_x(k), [[-1.0]]), (_x(k + 1), [[1.0]]), (KA, -dt * self.basis_a[k][None])], 0.0, sigma_m)

    def gaussian(self, k_end: int, sigma_m: float, sigma_s: float) -> gtsam.GaussianFactorGraph:
        """All factors of frames 0..k_end as one linear graph."""
        gfg = gtsam.GaussianFactorGraph()
        specs = self.priors()
        for k in range(k_end + 1):
            specs += self.sensor(k, sigma_s)
            if k < k_end:
                specs.append(self.motion(k, sigma_m))
        for blocks, b, sigma in specs:
            gfg.add(_jacobian(blocks, b, sigma))
        return gfg

    def solve(self, sigma_m: float, sigma_s: float) -> gtsam.VectorValues:
        """The whole log in one batch linear solve (what ISAM2 reaches incrementally)."""
        return self.gaussian(len(self.walk.command), sigma_m, sigma_s).optimize()


def _jacobian(blocks, b, sigma) -> gtsam.JacobianFactor:
    args = [x for k, a in blocks for x in (k, np.atleast_2d(np.asarray(a, float)))]
    b = np.atleast_1d(np.asarray(b, float)).reshape(-1, 1)
    return gtsam.JacobianFactor(*args, b, gtsam.noiseModel.Isotropic.Sigma(len(b), sigma))


def _container(blocks, b, sigma) -> gtsam.LinearContainerFactor:
    """A linear factor as a nonlinear one ISAM2 accepts; linearised at zero, so its error is exact anywhere."""
    lin = gtsam.Values()
    for k, a in blocks:
        lin.insert(k, np.zeros(np.atleast_2d(a).shape[1]))
    return gtsam.LinearContainerFactor(_jacobian(blocks, b, sigma), lin)


MOTION_SIGMA = 0.0005      # per frame, in command units x seconds (0.5 mm per frame for a command in m/s)
SENSOR_SIGMA = 0.1         # location units per reading


def graph_online(walk: Walk, motion_sigma: float = MOTION_SIGMA, sensor_sigma: float = SENSOR_SIGMA,
                 action_degree: int = ACTION_DEGREE,
                 sensor_degree: int = SENSOR_DEGREE, command_scale: float | None = None, every: float = 1.0,
                 batch: float = 0.5, progress=None) -> GraphResult:
    """The 1-D graph run online with ISAM2, one update per ``batch`` seconds of frames.

    The two sigmas are fixed settings, as the EKFS-EM paper fixes its motion noise and SCASM its
    lambda: maximising the evidence over them drives the sensor sigma to zero on these logs (the
    reading noise is heteroscedastic in location units and the speed error is correlated over a
    command, neither of which this model has). ISAM2's root holds the two models and is solved at
    every update, the locations once at the end. Linear factors, so no relinearisation is needed.
    """
    t0 = time.perf_counter()
    g = Graph1D(walk, action_degree, sensor_degree, command_scale)
    T = len(walk.command)
    params = gtsam.ISAM2Params()
    params.setFactorization("QR")
    params.enableRelinearization = False
    gn = gtsam.ISAM2GaussNewtonParams()
    gn.setWildfireThreshold(1e9)
    params.setOptimizationParams(gn)
    isam = gtsam.ISAM2(params)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for spec in g.priors():
        graph.add(_container(*spec))
    values.insert(_x(0), np.zeros(1))
    values.insert(KA, g.a0)
    values.insert(KS, np.zeros(g.ns))
    est_a, est_x = g.a0.copy(), 0.0
    hist, next_hist, next_update, updates = [], 0.0, 0.0, 0
    for k in range(T + 1):
        for spec in g.sensor(k, sensor_sigma):
            graph.add(_container(*spec))
        t = walk.t[k]
        if t >= next_update or k == T:
            isam.update(graph, values)
            updates += 1
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            est = isam.calculateEstimate([KA, KS])
            est_a = est.atVector(KA)
            next_update += batch
            if t >= next_hist or k == T:
                hist.append((float(t), est_a.copy(), est.atVector(KS).copy()))
                next_hist += every
            if progress is not None:
                progress.step(1)
        if k < T:
            graph.add(_container(*g.motion(k, motion_sigma)))
            est_x += walk.dt[k] * float(g.basis_a[k] @ est_a)
            values.insert(_x(k + 1), np.array([est_x]))
    est = isam.calculateBestEstimate()
    x = np.array([est.atVector(_x(k))[0] for k in range(T + 1)])
    return GraphResult(action=PolyModel(est.atVector(KA), g.c_scale), sensor=PolyModel(est.atVector(KS), g.o_scale),
                       x=x, action_std=np.sqrt(np.diag(isam.marginalCovariance(KA))),
                       sensor_std=np.sqrt(np.diag(isam.marginalCovariance(KS))),
                       motion_sigma=motion_sigma, sensor_sigma=sensor_sigma,
                       history=hist, seconds=time.perf_counter() - t0, updates=updates)
