"""Omnidirectional-robot test world: a self-contained simulator (numpy only).

A legged / mecanum-like robot gets body-frame velocity commands (vx, vy, w) at
10 Hz, moves under a continuous-time model integrated at 200 Hz (gains, offsets,
a quadratic forward term, Ornstein-Uhlenbeck slip, optional physical effects),
and a camera reports apparent landmark size ("reading", px) and bearing.
It writes a log bundle (landmarks/commands/observations/truth CSV + world_truth.json).

Written apart from casm_graph (without reading it) so it can serve as an
independent test world.
"""
import argparse
import csv
import json
import os

import numpy as np

DT_CMD, SUB = 0.1, 20                  # 10 Hz commands, 20 sub-steps -> 200 Hz physics
DT = DT_CMD / SUB
VMAX = (0.25, 0.15, 0.8)               # |vx| m/s, |vy| m/s, |w| rad/s
RATE = (0.04, 0.03, 0.2)               # max command change per step
SLIP_TAU, SLIP_STD = 0.5, (0.008, 0.005, 0.024)
FOV, RMIN, RMAX, P_DETECT, MAX_PER_STEP = np.radians(60.0), 0.4, 6.0, 0.8, 2
READ_STD, BEAR_STD = 1.5, 0.03
EFFECTS = ("none", "actuator_lag", "surface_friction", "camera_latency", "battery_fade")


def wrap(a):
    """Wrap angle(s) to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2 * np.pi)


def _clear(p, lms, r):
    return len(lms) == 0 or np.min(np.hypot(lms[:, 0] - p[0], lms[:, 1] - p[1])) >= r


def _random_point(rng, field, lms, margin, clearance):
    x0, x1, y0, y1 = field
    while True:
        p = (rng.uniform(x0 + margin, x1 - margin), rng.uniform(y0 + margin, y1 - margin))
        if _clear(p, lms, clearance):
            return p


def make_world(rng):
    """Field rectangle (origin off-centre), landmarks, gains, sensor constants, start pose."""
    W, H = rng.uniform(4, 9), rng.uniform(4, 9)
    x0, y0 = -rng.uniform(0.1, 0.9) * W, -rng.uniform(0.1, 0.9) * H
    field = (x0, x0 + W, y0, y0 + H)
    n = int(rng.integers(4, 8))
    pts = []
    while len(pts) < n:
        p = [rng.uniform(x0, x0 + W), rng.uniform(y0, y0 + H)]
        if rng.random() < 0.3:                       # some landmarks sit on an edge
            k = rng.integers(4)
            p[k // 2] = field[k]
        if _clear(p, np.array(pts), 1.0):
            pts.append(p)
    lms = np.array(pts)
    ids = [int(i) for i in rng.integers(10, 30) + np.cumsum(rng.integers(1, 3, n))]
    motion = dict(gx=rng.uniform(0.85, 1.15), gy=rng.uniform(0.7, 1.0), gw=rng.uniform(0.8, 1.15),
                  ox=rng.uniform(-0.01, 0.01), oy=rng.uniform(-0.01, 0.01),
                  ow=rng.uniform(-0.03, 0.03), qx=rng.uniform(-0.1, 0.1))
    sensor = dict(a=rng.uniform(150, 300), b=rng.uniform(0.05, 0.3), c=rng.uniform(2, 8))
    sx, sy = _random_point(rng, field, lms, 0.3, 0.3)
    start = (sx, sy, float(wrap(rng.uniform(-np.pi, np.pi))))
    return field, ids, lms, motion, sensor, start


def make_effect(rng, name, strength, field):
    """Draw every effect's parameters in a fixed order; keep the chosen one."""
    tau, s, delta, r = rng.uniform(0.1, 0.25), rng.uniform(0.15, 0.3), rng.uniform(0.06, 0.18), rng.uniform(0.01, 0.03)
    x0, x1, y0, y1 = field
    frac, aspect = rng.uniform(0.2, 0.4), rng.uniform(0.5, 2.0)
    area = frac * (x1 - x0) * (y1 - y0)
    pw = min(np.sqrt(area * aspect), x1 - x0)
    ph = min(area / pw, y1 - y0)
    px, py = rng.uniform(x0, x1 - pw), rng.uniform(y0, y1 - ph)
    eff = {"name": name}
    if name == "actuator_lag":
        tau = tau if strength is None else strength
        eff.update(strength=tau, taus=[tau, tau],
                   model="u1' = (cmd - u1)/tau1, u2' = (u1 - u2)/tau2; gains act on u2")
    elif name == "surface_friction":
        s = s if strength is None else strength
        eff.update(strength=s, patch=dict(xmin=px, xmax=px + pw, ymin=py, ymax=py + ph),
                   patch_fraction=pw * ph / ((x1 - x0) * (y1 - y0)),
                   model="inside patch: forward, lateral *= (1 - s); turn *= (1 - s/2)")
    elif name == "camera_latency":
        delta = delta if strength is None else strength
        eff.update(strength=delta, delta=delta, model="image taken at t - delta, stamped t")
    elif name == "battery_fade":
        r = r if strength is None else strength
        eff.update(strength=r, rate_per_minute=r, model="all velocities *= (1 - r * t_minutes)")
    else:
        eff.update(name="none", strength=None)
    return eff


class Policy:
    """Waypoint follower using omnidirectional motion: strafe / drive segments, stops, holds."""

    def __init__(self, rng, field, lms):
        self.rng, self.field, self.lms = rng, field, lms
        self.cmd = np.zeros(3)
        self.hold = 0
        self.mode = None

    def _new_segment(self, pose):
        rng = self.rng
        self.timer = 300
        self.scale = rng.uniform(0.5, 1.0)
        u = rng.random()
        if u < 0.12:
            self.mode, self.timer = "stop", int(rng.integers(5, 21))
            return
        self.wp = np.array(_random_point(rng, self.field, self.lms, 0.4, 0.3))
        self.mode = "strafe" if u < 0.5 else "drive"
        if self.mode == "strafe":           # hold a heading well off the travel direction
            e = self.wp - pose[:2]
            self.psi = np.arctan2(e[1], e[0]) + rng.choice([-1, 1]) * rng.uniform(0.6, 1.6)

    def step(self, pose):
        if self.hold > 0:
            self.hold -= 1
            return self.cmd.copy()
        if self.mode is not None and self.rng.random() < 0.04:
            self.hold = int(self.rng.integers(1, 5))
            return self.cmd.copy()
        if self.mode is None or self.timer <= 0:
            self._new_segment(pose)
        self.timer -= 1
        want = np.zeros(3)
        if self.mode != "stop":
            e = self.wp - pose[:2]
            dist = np.hypot(*e)
            if dist < 0.15:
                self._new_segment(pose)
                return self.step(pose)
            th, s = pose[2], self.scale
            if self.mode == "strafe":
                bx = np.cos(th) * e[0] + np.sin(th) * e[1]
                by = -np.sin(th) * e[0] + np.cos(th) * e[1]
                bx, by = bx / dist, by / dist
                v = min(0.6 * dist, VMAX[0] * s / max(abs(bx), 1e-6), VMAX[1] * s / max(abs(by), 1e-6))
                want = np.array([v * bx, v * by, np.clip(1.2 * wrap(self.psi - th), -0.8 * s, 0.8 * s)])
            else:
                err = wrap(np.arctan2(e[1], e[0]) - th)
                want = np.array([VMAX[0] * s * max(np.cos(err), 0.0) ** 2 * min(1.0, dist / 0.5),
                                 np.clip(0.3 * dist * np.sin(err), -0.05, 0.05),
                                 np.clip(1.5 * err, -VMAX[2], VMAX[2])])
        self.cmd = np.clip(self.cmd + np.clip(want - self.cmd, -np.array(RATE), RATE),
                           -np.array(VMAX), VMAX)
        return self.cmd.copy()


def simulate(n_steps, world, eff, rng):
    """Integrate the true motion at 200 Hz. Returns commands (n,3) and sub-step poses."""
    field, ids, lms, m, _, start = world
    policy = Policy(rng, field, lms)
    x, y, th = start
    slip = [0.0, 0.0, 0.0]
    lag1, lag2 = [0.0] * 3, [0.0] * 3
    a_ou = np.exp(-DT / SLIP_TAU)
    s_ou = [sd * np.sqrt(1 - a_ou ** 2) for sd in SLIP_STD]
    a_lag = 1 - np.exp(-DT / eff["taus"][0]) if eff["name"] == "actuator_lag" else None
    patch = eff.get("patch")
    cmds = np.zeros((n_steps, 3))
    poses = np.zeros((n_steps * SUB + 1, 3))
    poses[0] = (x, y, th)
    for k in range(n_steps):
        cmd = policy.step(np.array([x, y, th]))
        cmds[k] = cmd
        noise = rng.standard_normal((SUB, 3))
        for j in range(SUB):
            t = (k * SUB + j) * DT
            if a_lag is not None:
                for i in range(3):
                    lag1[i] += a_lag * (cmd[i] - lag1[i])
                    lag2[i] += a_lag * (lag1[i] - lag2[i])
                u = lag2
            else:
                u = cmd
            vf = m["gx"] * u[0] + m["ox"] + m["qx"] * u[0] * abs(u[0]) + slip[0]
            vl = m["gy"] * u[1] + m["oy"] + slip[1]
            om = m["gw"] * u[2] + m["ow"] + slip[2]
            if patch and patch["xmin"] <= x <= patch["xmax"] and patch["ymin"] <= y <= patch["ymax"]:
                s = eff["strength"]
                vf, vl, om = vf * (1 - s), vl * (1 - s), om * (1 - s / 2)
            if eff["name"] == "battery_fade":
                f = 1 - eff["strength"] * t / 60.0
                vf, vl, om = vf * f, vl * f, om * f
            hm = th + 0.5 * om * DT
            x += (vf * np.cos(hm) - vl * np.sin(hm)) * DT
            y += (vf * np.sin(hm) + vl * np.cos(hm)) * DT
            th += om * DT
            for i in range(3):
                slip[i] = a_ou * slip[i] + s_ou[i] * noise[j, i]
            poses[k * SUB + j + 1] = (x, y, th)
    return cmds, poses


def true_velocities(truth, commands):
    """Steady-state body velocity (forward, lateral, turn) of each command row (n, 3) under the world's motion
    model as world_truth.json records it (no slip, no effect)."""
    g, o, q = truth["motion"]["gains"], truth["motion"]["offsets"], truth["motion"]["qx"]
    u = np.asarray(commands, float)
    return np.column_stack([g["forward"] * u[:, 0] + o["forward"] + q * u[:, 0] * np.abs(u[:, 0]),
                            g["lateral"] * u[:, 1] + o["lateral"], g["turn"] * u[:, 2] + o["turn"]])


def sense(n_steps, world, eff, poses, rng):
    """Camera sightings stamped at command step times (pose taken at t - delta)."""
    _, ids, lms, _, sen, _ = world
    delta = eff.get("delta", 0.0)
    ts = np.arange(len(poses)) * DT
    rows = []
    for k in range(n_steps):
        t = k * DT_CMD
        tc = t - delta
        x, y, th = (np.interp(tc, ts, poses[:, i]) for i in range(3))
        dx, dy = lms[:, 0] - x, lms[:, 1] - y
        d = np.hypot(dx, dy)
        bear = wrap(np.arctan2(dy, dx) - th)
        detected = rng.random(len(lms)) < P_DETECT
        idx = np.flatnonzero((np.abs(bear) <= FOV) & (d >= RMIN) & (d <= RMAX) & detected)
        if len(idx) > MAX_PER_STEP:
            idx = rng.choice(idx, MAX_PER_STEP, replace=False)
        for i in sorted(idx, key=lambda i: ids[i]):
            reading = sen["a"] / (d[i] + sen["b"]) + sen["c"] + rng.normal(0, READ_STD)
            rows.append((t, ids[i], reading, float(wrap(bear[i] + rng.normal(0, BEAR_STD)))))
    return rows


def _write_csv(path, header, rows, fmts):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in rows:
            w.writerow([fm % v for fm, v in zip(fmts, r)])


def generate(out_dir, minutes=6.0, seed=0, effect=None, strength=None):
    """Simulate and write the log bundle to out_dir; return the world_truth dict."""
    effect = effect or "none"
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; choose from {EFFECTS}")
    world_ss, motion_ss, sensor_ss, effect_ss = np.random.SeedSequence(seed).spawn(4)
    world = make_world(np.random.default_rng(world_ss))
    field, ids, lms, motion, sensor, start = world
    eff = make_effect(np.random.default_rng(effect_ss), effect,
                      None if strength is None else float(strength), field)
    n = int(round(minutes * 60 / DT_CMD))
    cmds, poses = simulate(n, world, eff, np.random.default_rng(motion_ss))
    obs = sense(n, world, eff, poses, np.random.default_rng(sensor_ss))

    os.makedirs(out_dir, exist_ok=True)
    tk = np.arange(n + 1) * DT_CMD
    _write_csv(os.path.join(out_dir, "landmarks.csv"), ["landmark", "x", "y"],
               [(i, p[0], p[1]) for i, p in zip(ids, lms)], ("%d", "%.4f", "%.4f"))
    _write_csv(os.path.join(out_dir, "commands.csv"), ["t", "vx", "vy", "w"],
               [(tk[k], *cmds[k]) for k in range(n)], ("%.1f", "%.5f", "%.5f", "%.5f"))
    _write_csv(os.path.join(out_dir, "observations.csv"), ["t", "landmark", "reading", "bearing"],
               obs, ("%.1f", "%d", "%.3f", "%.5f"))
    tp = poses[::SUB]
    _write_csv(os.path.join(out_dir, "truth.csv"), ["t", "x", "y", "theta"],
               [(tk[k], tp[k, 0], tp[k, 1], float(wrap(tp[k, 2]))) for k in range(n + 1)],
               ("%.1f", "%.6f", "%.6f", "%.6f"))

    truth = {
        "seed": seed, "minutes": minutes, "steps": n, "sightings": len(obs),
        "dt_command": DT_CMD, "dt_physics": DT,
        "effect": eff,
        "field": dict(zip(("xmin", "xmax", "ymin", "ymax"), field)),
        "landmarks": [{"landmark": i, "x": p[0], "y": p[1]} for i, p in zip(ids, lms)],
        "start_pose": dict(zip(("x", "y", "theta"), start)),
        "motion": {
            "model": "forward = gx*vx + ox + qx*vx*|vx|; lateral = gy*vy + oy; turn = gw*w + ow "
                     "(offsets act at all times, also when stopped); plus OU slip per axis",
            "gains": {"forward": motion["gx"], "lateral": motion["gy"], "turn": motion["gw"]},
            "offsets": {"forward": motion["ox"], "lateral": motion["oy"], "turn": motion["ow"]},
            "qx": motion["qx"],
            "slip": {"time_constant": SLIP_TAU, "std": dict(zip(("forward", "lateral", "turn"), SLIP_STD))},
            "command_limits": dict(zip(("vx", "vy", "w"), VMAX)),
        },
        "sensor": {
            "formula": "reading = a / (d + b) + c; bearing = atan2 in body frame, wrapped to (-pi, pi]",
            "a": sensor["a"], "b": sensor["b"], "c": sensor["c"],
            "reading_noise_std": READ_STD, "bearing_noise_std": BEAR_STD,
            "fov_half_angle": float(FOV), "range_min": RMIN, "range_max": RMAX,
            "p_detect": P_DETECT, "max_per_step": MAX_PER_STEP, "rate_hz": 1 / DT_CMD,
        },
    }
    truth = json.loads(json.dumps(truth, default=float))
    with open(os.path.join(out_dir, "world_truth.json"), "w") as f:
        json.dump(truth, f, indent=2)
    return truth


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", choices=EFFECTS, default="none")
    ap.add_argument("--strength", type=float, default=None)
    a = ap.parse_args()
    t = generate(a.out, a.minutes, a.seed, a.effect, a.strength)
    print(f"wrote {a.out}: {t['steps']} steps, {t['sightings']} sightings, "
          f"{len(t['landmarks'])} landmarks, effect {t['effect']['name']} "
          f"(strength {t['effect']['strength']})")


if __name__ == "__main__":
    main()
