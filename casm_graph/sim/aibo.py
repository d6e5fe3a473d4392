"""The EKFS-EM paper's simulated Aibo protocol: a log bundle with its truth.

A 5.4 m x 3.6 m field with four beacons, the 40-action set, a new action every 5 s chosen to stay
on the field and even out counts, a head scanning side to side (one beacon at a time in view),
30 frames/s, beacon height in pixels from a pinhole camera model, noisy bearings. ``sensor`` keeps
only the reading ("range") or only the bearing ("bearing") of each sighting; the camera still has to see the beacon.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from casm_graph.io import log as logmod
from casm_graph.io.log import Log, LogError, wrap
from casm_graph.models.aibo import BEACONS, FIELD, attempted_table
from casm_graph.models.effects import get as get_effect

SENSORS = {"both": ["reading", "bearing"], "range": ["reading"], "bearing": ["bearing"]}   # the cells a log fills


def check_sensor(sensor) -> None:
    """Reject a sensor mode other than range, bearing or both, in one line."""
    if sensor not in SENSORS:
        raise LogError(f"sensor must be one of {', '.join(SENSORS)} (got {sensor!r})")


def channels(sensor: str) -> list[str]:
    """The observation columns a log of this sensor mode measures."""
    return list(SENSORS[sensor])


@dataclass
class Camera:
    """Pinhole camera on the robot's nose looking at a beacon's coloured band."""

    focal_px: float = 192.0          # ERS-7 at 208 x 160, ~45 deg vertical field of view
    band: tuple[float, float] = (0.2, 0.4)   # bottom and top of the beacon's band above ground (m)
    height: float = 0.28             # camera height (m)
    half_fov: float = 0.497          # horizontal half field of view (rad), 56.9 deg / 2
    min_range: float = 1.275         # the paper's recognisable distances
    max_range: float = 4.175

    def reading(self, d):
        """Beacon band height in pixels at distance ``d``: the angle it subtends times the focal length."""
        d = np.asarray(d, float)
        lo, hi = self.band
        return self.focal_px * (np.arctan((hi - self.height) / d) - np.arctan((lo - self.height) / d))


@dataclass
class SimConfig:
    """Everything the simulator draws from; every random choice comes from ``seed``."""

    minutes: float = 15.0
    seed: int = 0
    rate: float = 30.0                       # frames (and command steps) per second
    segment: float = 5.0                     # seconds per action
    reading_sigma: float = 1.0               # px
    bearing_sigma: float = 0.5               # rad
    motion_noise: tuple[float, float, float] = (0.002, 0.002, 0.004)   # per-step std (m, m, rad)
    detection_prob: float = 0.9
    pan_amplitude: float = 1.3               # rad
    pan_period: float = 3.0                  # s
    margin: float = 0.25                     # keep this far inside the field when choosing actions
    camera: Camera = field(default_factory=Camera)
    effects: dict[str, float] = field(default_factory=dict)
    extra_effects: tuple = ()                # user Effect classes (not registered) that ``effects`` may name
    sensor: str = "both"                     # "range" (readings only), "bearing" (bearings only) or "both"


def true_table(rng: np.random.Generator) -> np.ndarray:
    """(40, 3) true velocities: scaled attempted velocities with couplings and per-action quirks.

    Forward steps are faster than backward ones, turning drags the gait sideways and slows it,
    and each action has its own small offsets, so the table is no simple function of the commands.
    """
    att = attempted_table()
    ax, ay, aw = att.T
    vx = np.where(ax > 0, 0.40, 0.31) * ax * (1 - 0.15 * np.abs(aw)) - 0.03 * np.abs(ay)
    vy = 0.42 * ay * (1 - 0.2 * np.abs(ax)) + 0.05 * aw
    w = np.pi * aw * (1 - 0.12 * (ax**2 + ay**2)) + 0.10 * ay * ax
    table = np.column_stack([vx, vy, w])
    table += rng.normal(0.0, [0.015, 0.015, 0.04], size=table.shape)
    return table


def _rollout(pose: np.ndarray, v: np.ndarray, n: int, dt: float) -> np.ndarray:
    """Noise-free poses (n+1, 3) under constant body velocity ``v`` (the per-step model)."""
    th = pose[2] + v[2] * dt * np.arange(n + 1)
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dx = (c * v[0] - s * v[1]) * dt
    dy = (s * v[0] + c * v[1]) * dt
    x = pose[0] + np.concatenate([[0], np.cumsum(dx)])
    y = pose[1] + np.concatenate([[0], np.cumsum(dy)])
    return np.column_stack([x, y, th])


def _choose(pose, table, counts, n, dt, margin, rng) -> int:
    """Least-used action whose next segment stays on the field (the paper's exploration policy)."""
    hx, hy = FIELD[0] / 2 - margin, FIELD[1] / 2 - margin
    inside, end_dist = [], []
    for a, v in enumerate(table):
        path = _rollout(pose, v, n, dt)
        inside.append(np.all(np.abs(path[:, 0]) <= hx) and np.all(np.abs(path[:, 1]) <= hy))
        end_dist.append(np.hypot(path[-1, 0], path[-1, 1]))
    inside = np.array(inside)
    if not inside.any():
        return int(np.argmin(end_dist))
    cand = np.flatnonzero(inside)
    least = cand[counts[cand] == counts[cand].min()]
    return int(rng.choice(least))


def simulate(cfg: SimConfig) -> tuple[Log, dict]:
    """Run the protocol; return the log (with truth) and the truth model as a JSON-ready dict."""
    own = {cls.name: cls for cls in cfg.extra_effects}
    effects = [own[name]() if name in own else get_effect(name)() for name in cfg.effects]   # unknown names fail first
    for e in effects:
        e.restore({"extent": [-FIELD[0] / 2, -FIELD[1] / 2, FIELD[0] / 2, FIELD[1] / 2]})   # a field effect's extent
        if e.continuous_only:
            raise LogError(f"--effect {e.name}: needs continuous (v, w) commands; the floor protocol "
                           f"(--protocol floor) has it built in (rough regions)")
    if cfg.minutes <= 0:
        raise LogError(f"--minutes must be positive (got {cfg.minutes:g})")
    check_sensor(cfg.sensor)
    rng = np.random.default_rng(cfg.seed)
    eff_rng = np.random.default_rng([cfg.seed, 7])              # a separate stream: effects leave the rest alone
    thetas = [e.simulate_params(float(cfg.effects[e.name]), eff_rng) for e in effects]
    motion = [(e, th) for e, th in zip(effects, thetas) if e.channel == "motion"]
    sensor = [(e, th) for e, th in zip(effects, thetas) if e.channel == "sensor"]
    table = true_table(rng)
    dt = 1.0 / cfg.rate
    steps = int(round(cfg.minutes * 60 * cfg.rate))
    per_seg = int(round(cfg.segment * cfg.rate))
    cam = cfg.camera

    pose = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-0.6, 0.6), rng.uniform(-np.pi, np.pi)])
    poses = np.empty((steps + 1, 3))
    poses[0] = pose
    actions = np.empty(steps, dtype=np.int64)
    counts = np.zeros(len(table), int)
    noise = rng.normal(0.0, cfg.motion_noise, size=(steps, 3))
    v_true = np.empty((steps, 3))
    prev = None
    for k0 in range(0, steps, per_seg):
        n = min(per_seg, steps - k0)
        a = _choose(poses[k0], table, counts, n, dt, cfg.margin, rng)
        counts[a] += 1
        actions[k0:k0 + n] = a
        v_prev = table[a if prev is None or prev == a else prev]
        prev = a
        for k in range(k0, k0 + n):
            x, y, th = poses[k]
            v = table[a][None]
            ctx = {"t": np.array([k * dt]), "pose": poses[k][None], "since": np.array([(k - k0) * dt]),
                   "dt": np.array([dt]), "v_prev": v_prev[None]}
            for e, theta in motion:
                v = e.velocity(theta, v, ctx)
            v_true[k] = v[0]
            d = v[0] * dt + noise[k]
            c, s = np.cos(th), np.sin(th)
            poses[k + 1] = (x + c * d[0] - s * d[1], y + s * d[0] + c * d[1], th + d[2])

    t = np.arange(steps) * dt
    frame_t = np.arange(steps + 1) * dt
    pan = cfg.pan_amplitude * np.sin(2 * np.pi * frame_t / cfg.pan_period + rng.uniform(0, 2 * np.pi))
    frame_v = v_true[np.clip(np.arange(steps + 1) - 1, 0, steps - 1)]
    rel = np.empty((steps + 1, len(BEACONS), 2))
    heading = np.empty((steps + 1, len(BEACONS)))
    for j in range(len(BEACONS)):          # where each beacon really is, seen from where the camera really was
        ctx = {"t": frame_t, "landmark": np.full(steps + 1, j), "pan": pan, "velocity": frame_v}
        p, lm = poses, np.repeat(BEACONS[j][None], steps + 1, 0)
        for e, theta in sensor:
            p, lm = e.geometry(theta, p, lm, ctx)
        rel[:, j] = lm - p[:, :2]
        heading[:, j] = p[:, 2]
    dist = np.hypot(rel[..., 0], rel[..., 1])
    bearing = wrap(np.arctan2(rel[..., 1], rel[..., 0]) - heading)
    image = np.abs(wrap(bearing - pan[:, None]))
    visible = (image < cam.half_fov) & (dist >= cam.min_range) & (dist <= cam.max_range)
    image = np.where(visible, image, np.inf)
    seen = visible.any(axis=1) & (rng.random(steps + 1) < cfg.detection_prob)
    frames = np.flatnonzero(seen)
    which = np.argmin(image[frames], axis=1)
    d_seen = dist[frames, which]
    ctx = {"t": frame_t[frames], "landmark": which, "pan": pan[frames], "velocity": frame_v[frames],
           "pose": poses[frames], "distance": d_seen, "bearing": bearing[frames, which],
           "image_angle": wrap(bearing[frames, which] - pan[frames])}
    clean = cam.reading(d_seen)
    scale = np.ones(len(frames))
    for e, theta in sensor:
        clean = e.reading(theta, clean, ctx)
        scale = scale * e.reading_scale(theta, d_seen, ctx)
    reading = clean + rng.normal(0, cfg.reading_sigma, len(frames)) * scale
    obs_bearing = wrap(bearing[frames, which] + rng.normal(0, cfg.bearing_sigma, len(frames)))
    obs = {"landmark": which.astype(np.int64), "reading": reading, "bearing": obs_bearing,
           "n_landmarks": len(BEACONS)}
    for e, theta in sensor:
        obs = e.corrupt(theta, obs, eff_rng)
    which, reading, obs_bearing = obs["landmark"], obs["reading"], obs["bearing"]
    if cfg.sensor == "range":
        obs_bearing = np.full(len(obs_bearing), np.nan)
    elif cfg.sensor == "bearing":
        reading = np.full(len(reading), np.nan)

    poses[:, 2] = wrap(poses[:, 2])
    att = attempted_table()
    log = Log(
        landmark_ids=np.arange(len(BEACONS)), landmark_xy=BEACONS.copy(), t=t, action=actions,
        controls=None, control_names=(), obs_t=frame_t[frames], obs_landmark=which.astype(np.int64),
        obs_reading=reading, obs_bearing=obs_bearing, obs_pan=wrap(pan[frames]),
        attempted={a: att[a] for a in range(len(att))},
        truth=np.column_stack([frame_t, poses]),
    )
    d_grid = np.linspace(d_seen.min(), d_seen.max(), 200)
    truth = {
        "schema": "casm-graph/truth/1",
        "action_model": {"kind": "table",
                         "velocities": {str(a): table[a].tolist() for a in range(len(table))}},
        "motion_noise": list(cfg.motion_noise),
        "sensor_model": {
            "kind": "camera",
            "sensor": cfg.sensor,
            "channels": channels(cfg.sensor),
            "camera": asdict(cam),
            "reading_sigma": cfg.reading_sigma,
            "bearing_sigma": cfg.bearing_sigma,
            "distance_range": [float(d_seen.min()), float(d_seen.max())],
            "reading_poly_best_cubic": np.polynomial.polynomial.polyfit(
                d_grid, cam.reading(d_grid), 3).tolist(),
        },
        "effects": {e.name: e.describe(th) for e, th in zip(effects, thetas)},
        "simulation": {k: v for k, v in asdict(cfg).items() if k not in ("camera", "extra_effects")},
    }
    return log, truth


def write(log: Log, truth: dict, out: str | Path) -> Path:
    """Write the bundle plus truth_model.json."""
    d = logmod.write(log, out)
    (d / "truth_model.json").write_text(json.dumps(truth, indent=2))
    return d


def true_reading(truth: dict, d) -> np.ndarray:
    """The true sensor curve of a simulated log, from its truth_model.json."""
    cam = truth["sensor_model"]["camera"]
    return Camera(**{**cam, "band": tuple(cam["band"])}).reading(d)
