"""Independent robot-log generator: a test world written apart from casm_graph.

Why: calibration claims must hold on data the code was not tuned on. This module shares no code
with casm_graph (numpy and the standard library only) and simulates a differently built world:
continuous-time physics at 200 Hz, Ornstein-Uhlenbeck wheel slip instead of per-step Gaussian
increments, a non-polynomial sensor curve, effects produced by physics. It writes the log bundle
of INTERFACE.md section 1 plus world_truth.json.

The UNCATALOGED effects are ones no catalog is expected to name, each produced inside the 200 Hz
integration with geometry drawn from the seed and recorded under "geometry" in world_truth.json:
    heading_speed         forward *= 1 + s cos(theta - phi)                  geometry: phi
    position_drift_speed  forward *= 1 + s (x - x0) / field_width            geometry: x0, field_width
    time_speed            forward *= 1 + s sin(2 pi t / period + phase)      geometry: period, phase
                          (period 90-240 s: a slow oscillation, not a monotone fade)
    speed_turn            w += sign s v_forward (s in rad per metre)         geometry: sign, gain = sign s
                          (the chassis pulls to one side the more, the faster it goes)

    generate(out_dir, kind="table", minutes=6.0, seed=0, effect=None, strength=None, sensor="both")
    python tests/worlds/independent_world.py OUT --kind table --minutes 6 --seed 0 [--effect NAME]
"""
import argparse
import json
import math
import os
import sys

import numpy as np

PHYS_HZ = 200                                   # integration rate of the true motion
CMD_HZ = {"table": 10, "continuous": 20}        # command-row rate
MIN_RANGE, MAX_RANGE = 0.3, 8.0                 # sensor distance window (m)
FOV = {"table": math.radians(70.0), "continuous": math.pi}   # camera +-70 deg; range sensor all around
# a range-only table robot carries a ranging radio (all around, metres), not a camera whose blob size is read
P_DETECT = 0.5                                  # per landmark per command row
BEARING_SIGMA = 0.025                           # rad
READING_SIGMA = {"table": 1.0, "continuous": 0.05}   # px / m
SLIP_TAU, SLIP_FRAC = 0.5, 0.04                 # OU slip: time constant (s), fraction of speed
SLIP_FLOOR = (0.004, 0.004, 0.01)               # slip std at standstill (m/s, m/s, rad/s)
JITTER = (0.01, 0.01, 0.02)                     # white velocity jitter per 200 Hz sample
CMD_MAP = {"forward": {"gain": 0.92, "offset": 0.01}, "lateral": {"gain": 0.0, "offset": 0.0},
           "turn": {"gain": 1.06, "offset": 0.02}}   # continuous kind: true body velocity from (v, w)
SAFE_MARGIN = 0.5                               # the table policy keeps this far from the walls (m)
EFFECTS = {  # name: strength range drawn when strength is None
    "actuator_lag": (0.15, 0.4), "surface_friction": (0.15, 0.3), "camera_latency": (0.06, 0.2),
    "battery_fade": (0.01, 0.04), "lens_distortion": (0.2, 0.5),
    "range_dependent_noise": (0.3, 0.8), "false_detections": (0.03, 0.08),
    "landmark_offset": (0.15, 0.35), "heading_speed": (0.1, 0.2),
    "position_drift_speed": (0.1, 0.25),
    "time_speed": (0.1, 0.2),           # forward *= 1 + s sin(2 pi t / period + phase), period 90-240 s
    "speed_turn": (0.15, 0.35)}         # w += sign * s * v_forward, s in rad per metre, sign random
UNCATALOGED = ("heading_speed", "position_drift_speed", "time_speed", "speed_turn")
TIME_SPEED_PERIOD = (90.0, 240.0)       # s, range of the time_speed oscillation period


def _wrap(a):
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def _clearance(field, x, y):
    """Distance to the nearest wall (negative outside the field)."""
    return np.minimum(np.minimum(x - field["xmin"], field["xmax"] - x),
                      np.minimum(y - field["ymin"], field["ymax"] - y))


# ----------------------------------------------------------------------------- the world
def _draw_field(rng):
    """Rectangle with random sides; its centre shifted 10-35 % of a side away from the origin."""
    w, h = (float(v) for v in rng.uniform(5.0, 12.0, 2))
    cx = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.10, 0.35) * w)
    cy = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.10, 0.35) * h)
    return {"xmin": cx - w / 2, "xmax": cx + w / 2, "ymin": cy - h / 2, "ymax": cy + h / 2,
            "width": w, "height": h}


def _draw_landmarks(rng, f):
    """4-7 landmarks inside or on an edge of the field, >= 1.2 m apart, random distinct ids."""
    n = int(rng.integers(4, 8))
    pts = []
    while len(pts) < n:
        x, y = rng.uniform(f["xmin"], f["xmax"]), rng.uniform(f["ymin"], f["ymax"])
        if rng.random() < 0.4:                       # snap onto one of the four edges
            x, y = [(f["xmin"], y), (f["xmax"], y), (x, f["ymin"]), (x, f["ymax"])][rng.integers(4)]
        if all(math.hypot(x - px, y - py) >= 1.2 for px, py in pts):
            pts.append((float(x), float(y)))
    ids = [int(i) for i in rng.choice(np.arange(1, 200), n, replace=False)]
    return ids, np.array(pts)


def _draw_actions(rng):
    """15-25 actions with true body velocities (a few nearly pure turns) and attempted ones."""
    n = int(rng.integers(15, 26))
    n_turn = int(rng.integers(2, 4))
    vel = np.column_stack([rng.uniform(-0.15, 0.45, n), rng.uniform(-0.15, 0.15, n),
                           rng.uniform(-1.2, 1.2, n)])
    vel[:n_turn, :2] = rng.uniform(-0.005, 0.005, (n_turn, 2))
    vel[:n_turn, 2] = rng.choice([-1.0, 1.0], n_turn) * rng.uniform(0.4, 1.2, n_turn)
    vel = vel[rng.permutation(n)]
    ids = [int(i) for i in rng.choice(np.arange(0, 100), n, replace=False)]
    rot = rng.normal(0.0, 0.03, n)                   # attempted = true rotated/scaled a few percent
    sc = 1.0 + rng.normal(0.0, 0.03, (n, 3))
    att = np.column_stack([np.cos(rot) * vel[:, 0] + np.sin(rot) * vel[:, 1],
                           -np.sin(rot) * vel[:, 0] + np.cos(rot) * vel[:, 1], vel[:, 2]]) * sc
    return ids, vel, att


def _ranging(kind, sensor):
    """The sensor family a log of this kind and channel mode reads: "table" (camera) or "continuous" (radio)."""
    return "continuous" if sensor == "range" else kind


def _draw_sensor(rng, kind):
    """Non-polynomial apparent-size curve (table camera) or affine time-of-flight range (ranging radio)."""
    if kind == "table":
        p = {"a": float(rng.uniform(60, 120)), "b": float(rng.uniform(0.05, 0.3)),
             "c": float(rng.uniform(-2, 2))}
        return {"kind": "inverse", "formula": "a/(d+b)+c", **p}, \
            lambda d: p["a"] / (d + p["b"]) + p["c"]
    p = {"s": float(rng.uniform(1.02, 1.08)), "o": float(rng.uniform(-0.1, 0.2))}
    return {"kind": "affine", "formula": "s*d+o", **p}, lambda d: p["s"] * d + p["o"]


def _draw_effect(rng, effect, strength, f, lm_ids):
    """Strength (drawn if not given) and geometry of the one effect."""
    if effect is None:
        return None, {}
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: {', '.join(EFFECTS)}")
    drawn = float(rng.uniform(*EFFECTS[effect]))
    s = drawn if strength is None else float(strength)
    geom = {"uncataloged": effect in UNCATALOGED}
    if effect == "surface_friction":
        area = f["width"] * f["height"]
        while True:                                   # 20-40 % of the field, edges clear of the origin
            frac, aspect = rng.uniform(0.2, 0.4), rng.uniform(0.5, 2.0)
            pw = min(math.sqrt(frac * area * aspect), 0.9 * f["width"])
            ph = frac * area / pw
            if ph > 0.9 * f["height"]:
                continue
            x0 = rng.uniform(f["xmin"], f["xmax"] - pw)
            y0 = rng.uniform(f["ymin"], f["ymax"] - ph)
            if min(abs(x0), abs(x0 + pw), abs(y0), abs(y0 + ph)) >= 0.3:
                break
        geom["patch"] = {"xmin": float(x0), "xmax": float(x0 + pw), "ymin": float(y0),
                         "ymax": float(y0 + ph), "area_fraction": float(pw * ph / area)}
    elif effect == "landmark_offset":
        k = int(rng.integers(len(lm_ids)))
        ang = float(rng.uniform(-math.pi, math.pi))
        geom.update(landmark=lm_ids[k], index=k, direction=ang,
                    dx=s * math.cos(ang), dy=s * math.sin(ang))
    elif effect == "heading_speed":
        geom["phi"] = float(rng.uniform(-math.pi, math.pi))
    elif effect == "position_drift_speed":
        geom.update(x0=(f["xmin"] + f["xmax"]) / 2, field_width=f["width"])
    elif effect == "time_speed":
        geom.update(period=float(rng.uniform(*TIME_SPEED_PERIOD)), phase=float(rng.uniform(-math.pi, math.pi)))
    elif effect == "speed_turn":
        sign = float(rng.choice([-1.0, 1.0]))
        geom.update(sign=sign, gain=sign * s)       # rad/s of turn per m/s of forward speed
    return s, geom


# ----------------------------------------------------------------------------- physics
class _Physics:
    """Body dynamics; deterministic without noise, so the policy can use it to look ahead.

    Poses and velocities carry a leading batch axis (N, 3)."""

    def __init__(self, effect, strength, geom, field):
        self.effect, self.s, self.geom, self.field = effect, strength, geom, field

    def factor(self, pose, t):
        """Multiplicative speed effects at these poses and time."""
        f = np.ones((len(pose), 3))
        e, s, g = self.effect, self.s, self.geom
        if e == "surface_friction":
            p = g["patch"]
            on = ((pose[:, 0] >= p["xmin"]) & (pose[:, 0] <= p["xmax"])
                  & (pose[:, 1] >= p["ymin"]) & (pose[:, 1] <= p["ymax"]))
            f[on] *= 1.0 - s
        elif e == "battery_fade":
            f *= math.exp(-s * t / 60.0)
        elif e == "heading_speed":
            f[:, 0] *= 1.0 + s * np.cos(pose[:, 2] - g["phi"])
        elif e == "position_drift_speed":
            f[:, 0] *= 1.0 + s * (pose[:, 0] - g["x0"]) / g["field_width"]
        elif e == "time_speed":
            f[:, 0] *= 1.0 + s * math.sin(2 * math.pi * t / g["period"] + g["phase"])
        return f

    def step(self, pose, lag, nominal, t, dt, ou=None, jitter=None):
        """Advance pose in place by dt; nominal is the effect-free true body velocity."""
        if self.effect == "actuator_lag":             # critically damped: two cascaded 1st-order lags
            a = 1.0 - math.exp(-dt / self.s)
            lag[0] += a * (nominal - lag[0])
            lag[1] += a * (lag[0] - lag[1])
            v = lag[1].copy()
        else:
            v = np.array(nominal, dtype=float)
        if ou is not None:                            # slowly varying slip + white jitter
            lin = np.hypot(v[:, 0], v[:, 1])
            scale = np.column_stack([SLIP_FRAC * lin + SLIP_FLOOR[0], SLIP_FRAC * lin + SLIP_FLOOR[1],
                                     SLIP_FRAC * np.abs(v[:, 2]) + 0.02 * lin + SLIP_FLOOR[2]])
            v += ou * scale + jitter
        v *= self.factor(pose, t)
        if self.effect == "speed_turn":               # the chassis pulls aside in proportion to forward speed
            v[:, 2] += self.geom["gain"] * v[:, 0]
        th = pose[:, 2] + 0.5 * v[:, 2] * dt          # midpoint heading
        c, s = np.cos(th), np.sin(th)
        pose[:, 0] += (c * v[:, 0] - s * v[:, 1]) * dt
        pose[:, 1] += (s * v[:, 0] + c * v[:, 1]) * dt
        pose[:, 2] = _wrap(pose[:, 2] + v[:, 2] * dt)


class _TablePolicy:
    """Run each action 1.5-6 s; choose among actions whose look-ahead stays inside the field,
    least-used first, and near a wall prefer those that lead away from it."""

    def __init__(self, rng, phys, field, ids, vel):
        self.rng, self.phys, self.f, self.ids, self.vel = rng, phys, field, ids, vel
        self.counts = np.zeros(len(ids))
        self.left, self.k, self.segments = 0, 0, []

    def __call__(self, t, pose, lag):
        if self.left == 0:
            self._plan(t, pose, lag)
        self.left -= 1
        return self.vel[self.k][None], {"action": self.ids[self.k]}

    def _plan(self, t, pose, lag):
        n, dt = len(self.ids), 0.05
        P = np.repeat(pose, n, axis=0)
        L = np.repeat(lag, n, axis=1)
        c0 = float(_clearance(self.f, pose[0, 0], pose[0, 1]))
        floor = min(SAFE_MARGIN, c0) - 0.05
        fit, alive, c15 = np.full(n, 6.0), np.ones(n, bool), None
        for i in range(120):
            self.phys.step(P, L, self.vel, t + i * dt, dt)
            c = _clearance(self.f, P[:, 0], P[:, 1])
            bad = alive & (c < floor)
            fit[bad], alive = i * dt, alive & ~bad
            if i == 29:
                c15 = c.copy()
        ok = fit >= 1.5
        score = self.counts + self.rng.uniform(0.0, 0.9, n)
        if c0 < 1.0:
            score += 0.5 * (c15 < c0)
        if ok.any():
            k = int(np.argmin(np.where(ok, score, np.inf)))
            dur = min(self.rng.uniform(1.5, 6.0), fit[k])
        else:
            k, dur = int(np.argmax(fit)), 1.5
        rows = max(15, int(dur * CMD_HZ["table"] + 1e-9))
        self.k, self.left = k, rows
        self.counts[k] += 1
        self.segments.append([self.ids[k], round(t, 3), rows / CMD_HZ["table"]])


class _WaypointController:
    """Drive to random waypoints inside the field; outputs (v, w) commands."""

    def __init__(self, rng, field):
        self.rng, self.f, self.wp, self.vmax = rng, field, None, 0.4

    def _new_waypoint(self, x, y):
        f, m = self.f, 1.0
        while True:
            wp = (self.rng.uniform(f["xmin"] + m, f["xmax"] - m), self.rng.uniform(f["ymin"] + m, f["ymax"] - m))
            if math.hypot(wp[0] - x, wp[1] - y) > 1.0:
                break
        self.wp, self.vmax = wp, float(self.rng.uniform(0.2, 0.6))

    def __call__(self, t, pose, lag):
        x, y, th = pose[0]
        if self.wp is None or math.hypot(self.wp[0] - x, self.wp[1] - y) < 0.25:
            self._new_waypoint(x, y)
        dx, dy = self.wp[0] - x, self.wp[1] - y
        err = float(_wrap(math.atan2(dy, dx) - th))
        w = float(np.clip(1.2 * err, -1.5, 1.5))
        v = float(np.clip(self.vmax * min(1.0, math.hypot(dx, dy) / 0.8) * max(math.cos(err), 0.0) ** 2, 0, 0.6))
        fw, tn = CMD_MAP["forward"], CMD_MAP["turn"]
        nominal = np.array([[fw["gain"] * v + fw["offset"], 0.0, tn["gain"] * w + tn["offset"]]])
        return nominal, {"v": v, "w": w}


def _simulate(rng, kind, field, phys, policy, rows):
    """Integrate at 200 Hz; the policy is asked once per command row. Returns 200 Hz poses."""
    sub = PHYS_HZ // CMD_HZ[kind]
    dt, n = 1.0 / PHYS_HZ, rows * sub
    z = rng.standard_normal((n, 3))
    jit = rng.standard_normal((n, 3)) * np.array(JITTER)
    ou = rng.standard_normal((1, 3))
    m = 1.0
    pose = np.array([[rng.uniform(field["xmin"] + m, field["xmax"] - m),
                      rng.uniform(field["ymin"] + m, field["ymax"] - m), rng.uniform(-math.pi, math.pi)]])
    lag = np.zeros((2, 1, 3))
    e = math.exp(-dt / SLIP_TAU)
    fine = np.empty((n + 1, 3))
    fine[0] = pose[0]
    commands = []
    for k in range(rows):
        nominal, cmd = policy(k / CMD_HZ[kind], pose, lag)
        commands.append(cmd)
        for j in range(k * sub, (k + 1) * sub):
            ou = e * ou + math.sqrt(1 - e * e) * z[j:j + 1]
            phys.step(pose, lag, nominal, j * dt, dt, ou, jit[j:j + 1])
            fine[j + 1] = pose[0]
    return fine, commands


def _pose_at(fine, t):
    """True pose at times t, interpolated between 200 Hz samples."""
    u = np.clip(np.asarray(t) * PHYS_HZ, 0, len(fine) - 1)
    i = np.minimum(np.floor(u).astype(int), len(fine) - 2)
    a = (u - i)[:, None]
    p0, p1 = fine[i], fine[i + 1]
    out = p0 + a * (p1 - p0)
    out[:, 2] = _wrap(p0[:, 2] + a[:, 0] * _wrap(p1[:, 2] - p0[:, 2]))
    return out


def _observe(rng, kind, sensor, fine, rows, lm_ids, lm_true, curve, effect, s, min_range=MIN_RANGE, camera=None):
    """Sightings at command-row times, or on the camera's own clock (``camera``: rate in Hz, phase in s):
    visibility, detection, curve, noise and sensor effects."""
    if camera is None:
        t = np.arange(rows) / CMD_HZ[kind]
    else:
        t = camera[1] + np.arange(int((rows / CMD_HZ[kind] - camera[1]) * camera[0])) / camera[0]
    pose = _pose_at(fine, t - s if effect == "camera_latency" else t)
    dx = lm_true[None, :, 0] - pose[:, None, 0]
    dy = lm_true[None, :, 1] - pose[:, None, 1]
    d = np.hypot(dx, dy)
    brg = _wrap(np.arctan2(dy, dx) - pose[:, None, 2])
    fov = FOV[_ranging(kind, sensor)]
    seen = (d >= min_range) & (d <= MAX_RANGE) & (np.abs(brg) <= fov) & (rng.random(d.shape) < P_DETECT)
    kk, ll = np.nonzero(seen)
    dd, aa = d[kk, ll], brg[kk, ll]
    clean = curve(dd)
    if effect == "lens_distortion":
        clean = clean * (1.0 + s * aa ** 2)
    sig = READING_SIGMA[_ranging(kind, sensor)] * ((1.0 + s * dd) if effect == "range_dependent_noise" else 1.0)
    reading = clean + sig * rng.standard_normal(len(dd))
    bearing = _wrap(aa + BEARING_SIGMA * rng.standard_normal(len(dd)))
    lm = np.array(lm_ids)[ll]
    fake = np.zeros(len(dd), bool)
    if effect == "false_detections":
        fake = rng.random(len(dd)) < s
        m = int(fake.sum())
        span = curve(np.array([min_range, MAX_RANGE]))
        lm[fake] = rng.choice(lm_ids, m)
        reading[fake] = rng.uniform(span.min(), span.max(), m)
        bearing[fake] = rng.uniform(-fov, fov, m)
    lines = []
    for tk, li, r, b in zip(t[kk], lm, reading, bearing):
        lines.append(f"{tk:.3f},{li},{'' if sensor == 'bearing' else f'{r:.5f}'},"
                     f"{'' if sensor == 'range' else f'{b:.6f}'}")
    return lines, {"n_observations": len(lines), "n_false": int(fake.sum()),
                   "false_rows": [int(i) for i in np.nonzero(fake)[0]],
                   "sightings": {str(i): int((lm == i).sum()) for i in lm_ids}}


def _realized(poses, hz, actions):
    """Mean achieved body velocity per action (slip and effects included): the table the log
    itself supports, which differs from the effect-free one by slip that did not average out."""
    d = np.diff(poses, axis=0)
    dth = _wrap(d[:, 2])
    th = poses[:-1, 2] + dth / 2
    body = np.column_stack([np.cos(th) * d[:, 0] + np.sin(th) * d[:, 1],
                            -np.sin(th) * d[:, 0] + np.cos(th) * d[:, 1], dth]) * hz
    a = np.array(actions)
    return {str(i): [float(v) for v in body[a == i].mean(axis=0)] for i in sorted(set(actions))}


def _write(path, header, lines):
    with open(path, "w") as fh:
        fh.write(header + "\n" + "".join(line + "\n" for line in lines))


# ----------------------------------------------------------------------------- entry point
def generate(out_dir, kind="table", minutes=6.0, seed=0, effect=None, strength=None, sensor="both",
             min_range=MIN_RANGE, camera=None):
    """Write a complete log bundle into out_dir (new or empty) and return the truth dict (``min_range``: the
    closest a landmark is sighted, m; ``camera``: (rate Hz, phase s) of a camera on its own clock, None: a sighting
    time is a command row's)."""
    if kind not in CMD_HZ:
        raise ValueError(f"kind must be 'table' or 'continuous', not {kind!r}")
    if sensor not in ("both", "range", "bearing"):
        raise ValueError(f"sensor must be both, range or bearing, not {sensor!r}")
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: {', '.join(EFFECTS)}")
    if os.path.exists(out_dir) and (not os.path.isdir(out_dir) or os.listdir(out_dir)):
        raise ValueError(f"{out_dir} exists and is not an empty directory")
    rows = int(round(minutes * 60 * CMD_HZ[kind]))
    if rows < 2:
        raise ValueError("minutes too small")
    # one stream per part, all from default_rng(seed): the same seed gives the same field,
    # actions, sensor and noise whatever the effect
    root = np.random.default_rng(seed)
    r_world, r_effect, r_motion, r_policy, r_sensor = (
        np.random.default_rng(int(x)) for x in root.integers(0, 2 ** 63, 5))
    field = _draw_field(r_world)
    lm_ids, lm_map = _draw_landmarks(r_world, field)
    act_ids, vel, att = _draw_actions(r_world)
    curve_info, curve = _draw_sensor(r_world, _ranging(kind, sensor))
    s, geom = _draw_effect(r_effect, effect, strength, field, lm_ids)
    lm_true = lm_map.copy()
    if effect == "landmark_offset":
        lm_true[geom["index"]] += (geom["dx"], geom["dy"])
    phys = _Physics(effect, s, geom, field)
    if kind == "table":
        policy = _TablePolicy(r_policy, phys, field, act_ids, vel)
    else:
        policy = _WaypointController(r_policy, field)
    fine, commands = _simulate(r_motion, kind, field, phys, policy, rows)
    obs_lines, obs_stats = _observe(r_sensor, kind, sensor, fine, rows, lm_ids, lm_true, curve, effect, s,
                                    min_range, camera)

    os.makedirs(out_dir, exist_ok=True)
    hz, sub = CMD_HZ[kind], PHYS_HZ // CMD_HZ[kind]
    _write(os.path.join(out_dir, "landmarks.csv"), "landmark,x,y",
           [f"{i},{x:.6f},{y:.6f}" for i, (x, y) in zip(lm_ids, lm_map)])
    if kind == "table":
        _write(os.path.join(out_dir, "commands.csv"), "t,action",
               [f"{k / hz:.3f},{c['action']}" for k, c in enumerate(commands)])
        _write(os.path.join(out_dir, "actions.csv"), "action,vx_cmd,vy_cmd,w_cmd",
               [f"{i},{a[0]:.6f},{a[1]:.6f},{a[2]:.6f}" for i, a in zip(act_ids, att)])
    else:
        _write(os.path.join(out_dir, "commands.csv"), "t,v,w",
               [f"{k / hz:.3f},{c['v']:.6f},{c['w']:.6f}" for k, c in enumerate(commands)])
    _write(os.path.join(out_dir, "observations.csv"), "t,landmark,reading,bearing", obs_lines)
    _write(os.path.join(out_dir, "truth.csv"), "t,x,y,theta",
           [f"{k / hz:.3f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for k, p in enumerate(fine[::sub])])

    d = np.linspace(min_range, MAX_RANGE, 40)
    truth = {
        "generator": "tests/worlds/independent_world.py", "kind": kind, "seed": seed,
        "minutes": minutes, "sensor": sensor, "field": field,
        "landmarks": {"map": {str(i): [float(x), float(y)] for i, (x, y) in zip(lm_ids, lm_map)},
                      "true": {str(i): [float(x), float(y)] for i, (x, y) in zip(lm_ids, lm_true)}},
        "effect": effect, "strength": s, "geometry": geom,
        "sensor_curve": {**curve_info, "samples": [[float(a), float(b)] for a, b in zip(d, curve(d))]},
        "noise": {"reading_sigma": READING_SIGMA[_ranging(kind, sensor)], "bearing_sigma": BEARING_SIGMA,
                  "slip_tau": SLIP_TAU, "slip_fraction": SLIP_FRAC, "slip_floor": list(SLIP_FLOOR),
                  "jitter": list(JITTER)},
        "sensing": {"p_detect": P_DETECT, "fov": FOV[_ranging(kind, sensor)], "min_range": min_range,
                    "max_range": MAX_RANGE},
        "rates": {"physics_hz": PHYS_HZ, "command_hz": hz, "camera": camera},
        "stats": {"fraction_outside": float(np.mean(_clearance(field, fine[:, 0], fine[:, 1]) < 0)),
                  **obs_stats},
    }
    if kind == "table":
        truth["velocities"] = {str(i): [float(v) for v in row] for i, row in zip(act_ids, vel)}
        truth["attempted"] = {str(i): [float(v) for v in row] for i, row in zip(act_ids, att)}
        truth["segments"] = policy.segments
        truth["realized_velocities"] = _realized(fine[::sub], hz, [c["action"] for c in commands])
    else:
        truth["command_map"] = CMD_MAP
    with open(os.path.join(out_dir, "world_truth.json"), "w") as fh:
        json.dump(truth, fh, indent=1)
    return truth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--kind", choices=sorted(CMD_HZ), default="table")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", default=None)
    ap.add_argument("--strength", type=float, default=None)
    ap.add_argument("--sensor", choices=["both", "range", "bearing"], default="both")
    ap.add_argument("--min-range", type=float, default=MIN_RANGE, help="closest sighting, m")
    ap.add_argument("--camera", type=float, nargs=2, metavar=("HZ", "PHASE"),
                    help="a camera on its own clock: its rate and the time of its first frame, s")
    a = ap.parse_args(argv)
    try:
        truth = generate(a.out, a.kind, a.minutes, a.seed, a.effect, a.strength, a.sensor, a.min_range, a.camera)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    st = truth["stats"]
    print(f"wrote {a.out}: {truth['kind']}, effect={truth['effect']} strength={truth['strength']}, "
          f"{st['n_observations']} observations, fraction outside {st['fraction_outside']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
