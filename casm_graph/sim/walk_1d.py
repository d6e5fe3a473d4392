"""The SCASM paper's 1-D protocol: an Aibo walking toward and away from one beacon.

A random command in [0, 300] going forward or [-300, 0] going back, held 3 s; the robot turns
around when the beacon looks too big or too small; 30 frames/s, beacon height in pixels. The true
command-to-velocity map is smooth but not a polynomial (saturating, asymmetric, with a ripple) and
the true height curve has a small non-geometric wobble, tuned so the best quartic/cubic fits miss
them by about as much as the paper's measured models (7.2 mm/s, 38.6 mm).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from casm_graph.io.log import Log, LogError
from casm_graph.sim.aibo import write  # noqa: F401  (same bundle + truth_model.json writer)

# The paper's evaluation grids: commands every 20 from -300 to 300, distances every 0.2 m from 1.2 to 3.6 m.
COMMAND_GRID = np.arange(-300.0, 301.0, 20.0)
DISTANCE_GRID = np.round(np.arange(1.2, 3.61, 0.2), 3)


def true_velocity(c) -> np.ndarray:
    """Actual walking velocity (mm/s) for command ``c`` (the Aibo's walk parameter, mm/s attempted)."""
    c = np.asarray(c, float)
    return np.where(c >= 0, 350.0 * np.tanh(c / 180.0), 310.0 * np.tanh(c / 165.0)) + 3.0 * np.sin(c / 30.0)


@dataclass
class Sim1DConfig:
    """Everything the 1-D protocol draws from; every random choice comes from ``seed``."""

    minutes: float = 2.5
    seed: int = 0
    rate: float = 30.0                  # frames and command steps per second
    segment: float = 3.0                # seconds per command
    focal_px: float = 384.0             # ERS-7 camera at full resolution
    beacon_height: float = 0.2          # height of the coloured band (m)
    wobble_px: float = 0.45             # non-geometric part of the height curve (px)
    reading_sigma: float = 1.0          # px
    bearing_sigma: float = 0.02         # rad (the walk keeps turning toward the beacon)
    speed_jitter: float = 0.03          # relative speed change per command execution
    step_noise: float = 0.001           # m per frame
    near: float = 1.25                  # turn-around distances (m), applied to the seen height
    far: float = 3.55
    detection_prob: float = 0.95


def true_reading(d, cfg: Sim1DConfig | None = None) -> np.ndarray:
    """Noise-free beacon height (px) at distance ``d`` (m)."""
    cfg = cfg or Sim1DConfig()
    d = np.asarray(d, float)
    geo = cfg.focal_px * (np.arctan(0.12 / d) - np.arctan(-0.08 / d)) * cfg.beacon_height / 0.2
    return geo + cfg.wobble_px * np.sin(2 * np.pi * d / 1.1)


def simulate(cfg: Sim1DConfig) -> tuple[Log, dict]:
    """Run the protocol; the robot stands at (-d, 0) facing the beacon at the origin."""
    if cfg.minutes <= 0:
        raise LogError(f"--minutes must be positive (got {cfg.minutes:g})")
    rng = np.random.default_rng(cfg.seed)
    dt = 1.0 / cfg.rate
    steps = int(round(cfg.minutes * 60 * cfg.rate))
    per_seg = int(round(cfg.segment * cfg.rate))
    r_near, r_far = true_reading(cfg.near, cfg), true_reading(cfg.far, cfg)
    d = np.empty(steps + 1)
    d[0] = rng.uniform(1.6, 3.2)
    cmd = np.empty(steps)
    going = 1.0 if rng.random() < 0.5 else -1.0          # +1: forward (toward the beacon)
    seen = np.zeros(steps + 1, bool)
    reading = np.full(steps + 1, np.nan)
    recent: list[float] = []
    c, gain, left = 0.0, 1.0, 0
    for k in range(steps + 1):
        if rng.random() < cfg.detection_prob:
            seen[k] = True
            reading[k] = true_reading(d[k], cfg) + rng.normal(0, cfg.reading_sigma)
            recent = (recent + [reading[k]])[-5:]
        if k == steps:
            break
        h = np.mean(recent) if recent else np.inf
        turn = (going > 0 and h > r_near) or (going < 0 and h < r_far)
        if turn:
            going = -going
        if left == 0 or turn:
            c = going * rng.uniform(0, 300)
            gain = 1.0 + cfg.speed_jitter * rng.normal()
            left = per_seg
        left -= 1
        cmd[k] = c
        v = gain * true_velocity(c) / 1000.0
        d[k + 1] = d[k] - v * dt + rng.normal(0, cfg.step_noise)
    frame_t = np.arange(steps + 1) * dt
    frames = np.flatnonzero(seen)
    bearing = rng.normal(0, cfg.bearing_sigma, len(frames))
    truth_xy = np.column_stack([frame_t, -d, np.zeros(steps + 1), np.zeros(steps + 1)])
    log = Log(landmark_ids=np.array([0]), landmark_xy=np.zeros((1, 2)), t=frame_t[:-1], action=None,
              controls=np.column_stack([cmd / 1000.0, np.zeros(steps)]), control_names=("v", "w"),
              obs_t=frame_t[frames], obs_landmark=np.zeros(len(frames), np.int64),
              obs_reading=reading[frames], obs_bearing=bearing, truth=truth_xy)
    vg = true_velocity(COMMAND_GRID)
    rg = true_reading(DISTANCE_GRID, cfg)
    truth = {
        "schema": "casm-graph/truth/1",
        "protocol": "scasm_1d",
        "action_model": {"kind": "scasm_1d", "command_unit": "m/s attempted (commands.csv v)",
                         "commands": (COMMAND_GRID / 1000.0).tolist(), "velocities": (vg / 1000.0).tolist(),
                         "best_quartic_rms_mm_s": _best_poly_rms(COMMAND_GRID, vg, 4)},
        "sensor_model": {"kind": "scasm_1d", "distances": DISTANCE_GRID.tolist(), "readings": rg.tolist(),
                         "reading_sigma": cfg.reading_sigma, "bearing_sigma": cfg.bearing_sigma,
                         "best_cubic_rms_mm": _best_poly_rms(rg, 1000 * DISTANCE_GRID, 3)},
        "simulation": asdict(cfg),
    }
    return log, truth


def _best_poly_rms(x, y, degree) -> float:
    p = np.polynomial.polynomial.polyfit(x, y, degree)
    return float(np.sqrt(np.mean((np.polynomial.polynomial.polyval(x, p) - y) ** 2)))
