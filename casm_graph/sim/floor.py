"""A wheeled robot on a floor whose motion noise differs by region (the MCL paper's set-up).

Differential drive, each step a translation r then a rotation theta (Milstein & Wang):
r ~ N(r_cmd, k_r |r_cmd|), theta ~ N(theta_cmd, k_t |theta_cmd| + k_d |r_cmd|) (variances), with
(k_r, k_t, k_d) taken from the region of a grid the robot is in. Commands (v, w) steer it between
random waypoints; range and bearing to known landmarks in front of it, sometimes. A range-only
sensor (``sensor="range"``, radio or UWB like) sees landmarks all around it, within ``max_range``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from casm_graph.io.log import Log, LogError, wrap
from casm_graph.models.effects.regional_motion_noise import region_of
from casm_graph.sim.aibo import channels, check_sensor

SMOOTH = (0.002, 0.01, 0.002)         # k_r (m), k_t (rad), k_d (rad^2/m): a hard floor
ROUGH_FACTOR = 10.0                   # variance factor of the rough regions (carpet, gravel)


@dataclass
class FloorConfig:
    """Everything the floor simulator draws from; every random choice comes from ``seed``."""

    minutes: float = 10.0
    seed: int = 0
    dt: float = 0.5                           # s per command step
    size: tuple[float, float] = (12.0, 8.0)   # m
    grid: tuple[int, int] = (3, 2)            # regions along x and y
    rough: tuple[int, ...] = (1, 3)           # region ids (row-major from the x = 0, y = 0 corner)
    smooth: tuple[float, float, float] = SMOOTH
    rough_factor: float = ROUGH_FACTOR
    n_landmarks: int = 14
    max_range: float = 5.0
    half_fov: float = np.pi / 2
    detect_prob: float = 0.2
    range_sigma: float = 0.05                 # m
    bearing_sigma: float = 0.02               # rad
    speed: float = 0.4                        # m/s cruising
    margin: float = 0.8                       # waypoints this far inside the walls
    lag: float = 0.0                          # s: the velocity follows the command through a first-order lag
    lens_k: float = 0.0                       # the range reads (1 + lens_k bearing^2) times the distance
    sensor: str = "both"                      # "range", "bearing" or "both": which cells the log fills
    range_scale: float = 1.0                  # reading = range_offset + range_scale * d + noise (time of flight)
    range_offset: float = 0.0                 # m
    nlos_fraction: float = 0.0                # this fraction of readings is not line of sight: ...
    nlos_scale: float = 1.0                   # ... an extra exponential error of this mean (m), always positive
    region_k: list = field(default_factory=list)   # filled by ``region_params``


def region_params(cfg: FloorConfig) -> np.ndarray:
    """(R, 3) true (k_r, k_t, k_d) per region."""
    k = np.tile(np.asarray(cfg.smooth, float), (cfg.grid[0] * cfg.grid[1], 1))
    k[list(cfg.rough)] *= cfg.rough_factor
    return k


def step(pose: np.ndarray, r: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Translate by ``r`` along the heading halfway through the turn ``theta``, and turn (poses (n, 3)): the chord
    of the arc a velocity held over the step drives."""
    c, s = np.cos(pose[..., 2] + 0.5 * theta), np.sin(pose[..., 2] + 0.5 * theta)
    return np.stack([pose[..., 0] + r * c, pose[..., 1] + r * s, wrap(pose[..., 2] + theta)], axis=-1)


def landmarks(cfg: FloorConfig, rng: np.random.Generator) -> np.ndarray:
    """Landmarks placed uniformly over the floor."""
    W, H = cfg.size
    n = cfg.n_landmarks
    xy = np.column_stack([rng.uniform(0.3, W - 0.3, n), rng.uniform(0.3, H - 0.3, n)])
    return xy


def check(cfg: FloorConfig) -> None:
    """Reject settings the floor simulator cannot run with, in one line."""
    if cfg.minutes <= 0:
        raise LogError(f"--minutes must be positive (got {cfg.minutes:g})")
    check_sensor(cfg.sensor)
    if not isinstance(cfg.n_landmarks, (int, np.integer)) or isinstance(cfg.n_landmarks, bool) or cfg.n_landmarks < 1:
        raise LogError(f"floor simulator: n_landmarks must be a whole number of at least 1 (got {cfg.n_landmarks})")
    if not cfg.range_scale > 0:
        raise LogError(f"floor simulator: range_scale must be positive (got {cfg.range_scale:g})")
    if not 0 <= cfg.nlos_fraction <= 1:
        raise LogError(f"floor simulator: nlos_fraction must be between 0 and 1 (got {cfg.nlos_fraction:g})")
    if not cfg.nlos_scale > 0:
        raise LogError(f"floor simulator: nlos_scale must be positive (got {cfg.nlos_scale:g})")


def simulate(cfg: FloorConfig) -> tuple[Log, dict]:
    """Drive between random waypoints; return the log (with truth) and the truth as a JSON-ready dict."""
    check(cfg)
    rng = np.random.default_rng(cfg.seed)
    W, H = cfg.size
    K = region_params(cfg)
    lm = landmarks(cfg, rng)
    steps = int(round(cfg.minutes * 60 / cfg.dt))
    pose = np.array([W / 2, H / 2, rng.uniform(-np.pi, np.pi)])
    poses = np.empty((steps + 1, 3))
    poses[0] = pose
    cmd = np.empty((steps, 2))
    goal = rng.uniform([cfg.margin, cfg.margin], [W - cfg.margin, H - cfg.margin])
    speed = cfg.speed
    vel = np.zeros(2)
    keep = np.exp(-cfg.dt / cfg.lag) if cfg.lag > 0 else 0.0
    for k in range(steps):
        p = poses[k]
        to = goal - p[:2]
        if np.hypot(*to) < 0.5:
            goal = rng.uniform([cfg.margin, cfg.margin], [W - cfg.margin, H - cfg.margin])
            speed = cfg.speed * rng.uniform(0.6, 1.2)
            to = goal - p[:2]
        err = wrap(np.arctan2(to[1], to[0]) - p[2])
        w = float(np.clip(1.5 * err, -0.8, 0.8))
        v = speed * (0.5 + 0.5 * max(np.cos(err), 0.0))
        cmd[k] = (v, w)
        vel = cmd[k] if k == 0 else keep * vel + (1 - keep) * cmd[k]
        r_c, t_c = vel[0] * cfg.dt, vel[1] * cfg.dt
        kr, kt, kd = K[region_of(p[:2], cfg.size, cfg.grid)[0]]
        r = r_c + rng.normal() * np.sqrt(kr * abs(r_c))
        th = t_c + rng.normal() * np.sqrt(kt * abs(t_c) + kd * abs(r_c))
        poses[k + 1] = step(p, r, th)
    t = np.arange(steps + 1) * cfg.dt
    all_around = cfg.sensor == "range"                # a range-only sensor sees landmarks all around it
    rows = []
    for k in range(1, steps + 1):                     # observations at each pose after a move
        rel = lm - poses[k, :2]
        d = np.hypot(rel[:, 0], rel[:, 1])
        b = wrap(np.arctan2(rel[:, 1], rel[:, 0]) - poses[k, 2])
        in_view = (d < cfg.max_range) & (all_around | (np.abs(b) < cfg.half_fov))
        vis = np.flatnonzero(in_view & (rng.random(len(lm)) < cfg.detect_prob))
        for j in vis:
            rows.append((t[k], j, cfg.range_offset + cfg.range_scale * d[j] * (1 + cfg.lens_k * b[j] ** 2)
                         + rng.normal(0, cfg.range_sigma), wrap(b[j] + rng.normal(0, cfg.bearing_sigma))))
    obs = np.array(rows, float).reshape(-1, 4)
    if cfg.nlos_fraction > 0:                         # a separate stream: the rest of the log stays as without NLOS
        nlos_rng = np.random.default_rng([cfg.seed, 11])
        hit = nlos_rng.random(len(obs)) < cfg.nlos_fraction
        obs[:, 2] += np.where(hit, nlos_rng.exponential(cfg.nlos_scale, len(obs)), 0.0)
    if cfg.sensor == "range":
        obs[:, 3] = np.nan
    elif cfg.sensor == "bearing":
        obs[:, 2] = np.nan
    log = Log(landmark_ids=np.arange(len(lm)), landmark_xy=lm, t=t[:-1], action=None, controls=cmd,
              control_names=("v", "w"), obs_t=obs[:, 0], obs_landmark=obs[:, 1].astype(np.int64),
              obs_reading=obs[:, 2], obs_bearing=obs[:, 3], truth=np.column_stack([t, poses]))
    c = asdict(cfg)
    c["region_k"] = K.tolist()
    truth = {
        "schema": "casm-graph/truth/1",
        "protocol": "floor",
        "motion_model": {"kind": "differential_drive_regions", "parameters": ["k_r", "k_t", "k_d"],
                         "size": list(cfg.size), "grid": list(cfg.grid), "region_k": K.tolist(),
                         "rough": list(cfg.rough)},
        "sensor_model": {"kind": "range_bearing", "sensor": cfg.sensor, "channels": channels(cfg.sensor),
                         "range_sigma": cfg.range_sigma, "bearing_sigma": cfg.bearing_sigma,
                         "reading_poly": [cfg.range_offset, cfg.range_scale], "range_scale": cfg.range_scale,
                         "range_offset": cfg.range_offset, "lens_k": cfg.lens_k, "nlos_fraction": cfg.nlos_fraction,
                         "nlos_scale": cfg.nlos_scale, "max_range": cfg.max_range, "detect_prob": cfg.detect_prob,
                         "half_fov": float(np.pi if all_around else cfg.half_fov), "n_landmarks": int(cfg.n_landmarks)},
        "simulation": c,
    }
    return log, truth
