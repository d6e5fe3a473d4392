#!/usr/bin/env python3
"""Independent differential-drive test world for casm-graph (numpy only).

python wheel_world.py OUT --minutes M --seed S [--effect NAME] [--sensor range|rssi|bearing]

Writes OUT/landmarks.csv, commands.csv (t,v,w), observations.csv (t,landmark,reading,bearing),
truth.csv (t,x,y,theta at 50 Hz), obs_truth.csv (true distance of each sighting, for scoring only),
cmd_truth.csv (steady-state true velocities of each logged command, for scoring only) and
world_truth.json.

Physics: commands (v, w) -> wheel set-points with the firmware's NOMINAL track width (0.4 m),
deadband on each set-point, per-wheel gain, saturation at vmax, first-order wheel response,
multiplicative slip noise (OU process) per wheel, true track width for the kinematics; integrated at
200 Hz. Sensor on its own clock.
"""
import argparse
import json
import math
import os

import numpy as np

EFFECTS = ["none", "battery_fade", "surface_friction", "actuator_lag", "camera_latency",
           "landmark_offset"]
B_NOMINAL = 0.4   # the firmware's idea of the track width


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def wheel_targets(v, w, t, P, eff):
    """steady-state wheel speeds (before slip) for command (v, w) at time t."""
    sl = v - w * B_NOMINAL / 2.0
    sr = v + w * B_NOMINAL / 2.0
    fade = 1.0
    if eff["name"] == "battery_fade":
        fade = max(0.2, 1.0 - eff["rate_per_min"] * (t - P["t0"]) / 60.0)
    vmax = P["vmax"] * fade
    out = []
    for s, g in ((sl, P["gain_l"]), (sr, P["gain_r"])):
        if abs(s) < P["deadband"]:
            out.append(0.0)
            continue
        u = g * fade * s
        out.append(min(vmax, max(-vmax, u)))
    return out[0], out[1]


def on_carpet(x, y, eff):
    if eff["name"] != "surface_friction":
        return False
    x0, y0, x1, y1 = eff["patch"]
    return x0 <= x <= x1 and y0 <= y <= y1


def steady_body(v, w, t, P, eff, x=None, y=None):
    l, r = wheel_targets(v, w, t, P, eff)
    if x is not None and on_carpet(x, y, eff):
        k = 1.0 - eff["extra_slip"]
        l, r = l * k, r * k
    return (l + r) / 2.0, (r - l) / P["track"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", default="none", choices=EFFECTS)
    ap.add_argument("--sensor", default="range", choices=["range", "rssi", "bearing"])
    ap.add_argument("--base-tau", type=float, default=0.05,
                    help="wheel response time constant without actuator_lag (default 0.05 s)")
    ap.add_argument("--no-slip", action="store_true", help="control runs: no wheel slip noise")
    a = ap.parse_args()

    # world draws use a stream that does not depend on effect/sensor, so the same seed gives the
    # same robot and field across effects; effect parameters come from a separate stream
    rng = np.random.default_rng(a.seed)
    erng = np.random.default_rng([a.seed, 7919])
    nrng = np.random.default_rng([a.seed, 104729])   # noise stream

    # ---------------- field and landmarks
    W, H = rng.uniform(6, 15, size=2)
    x0 = -rng.uniform(0.1, 0.4) * W       # origin inside the field, not at its centre
    y0 = -rng.uniform(0.1, 0.4) * H
    field = [x0, y0, x0 + W, y0 + H]
    nl = int(rng.integers(5, 10))
    ids = np.sort(rng.choice(np.arange(1, 60), size=nl, replace=False))
    lm = np.column_stack([rng.uniform(x0 + 0.3, x0 + W - 0.3, nl),
                          rng.uniform(y0 + 0.3, y0 + H - 0.3, nl)])

    # ---------------- robot
    P = dict(track=float(rng.uniform(0.3, 0.5)), gain_l=float(rng.uniform(0.9, 1.1)),
             gain_r=float(rng.uniform(0.9, 1.1)), vmax=float(rng.uniform(0.6, 0.8)),
             deadband=float(rng.uniform(0.01, 0.02)), tau=a.base_tau,
             slip_sigma=float(rng.uniform(0.02, 0.04)), slip_corr_s=0.3,
             t0=float(np.round(rng.uniform(0, 100), 3)))
    # sensor
    S = dict(kind=a.sensor, min_range=0.3, max_range=8.0, rate_hz=5.0, dropout=0.05,
             clock_offset=float(rng.uniform(0, 0.2)), clock_drift=float(rng.uniform(-2e-3, 2e-3)))
    if a.sensor == "range":
        S.update(scale=float(rng.uniform(1.0, 1.04)), bias=float(rng.uniform(0.0, 0.08)),
                 reading_sigma=float(rng.uniform(0.03, 0.08)),
                 bearing_sigma=float(rng.uniform(0.01, 0.03)))
    elif a.sensor == "rssi":
        S.update(n=float(rng.uniform(1.8, 2.5)), A=float(rng.uniform(-50, -40)),
                 reading_sigma=float(rng.uniform(2, 4)), bearing_sigma=None)
    else:
        S.update(reading_sigma=None, bearing_sigma=float(rng.uniform(0.01, 0.03)))

    # ---------------- effect
    eff = {"name": a.effect}
    lm_true = lm.copy()
    if a.effect == "battery_fade":
        eff["rate_per_min"] = float(erng.uniform(0.01, 0.03))
    elif a.effect == "surface_friction":
        pw, ph = erng.uniform(0.3, 0.5) * W, erng.uniform(0.3, 0.5) * H
        px, py = erng.uniform(x0 + 0.5, x0 + W - 0.5 - pw), erng.uniform(y0 + 0.5, y0 + H - 0.5 - ph)
        eff["patch"] = [float(px), float(py), float(px + pw), float(py + ph)]
        eff["extra_slip"] = float(erng.uniform(0.15, 0.30))
    elif a.effect == "actuator_lag":
        P["tau"] = float(erng.uniform(0.2, 0.35))
        eff["tau"] = P["tau"]
    elif a.effect == "camera_latency":
        eff["latency_s"] = float(erng.uniform(0.05, 0.15))
    elif a.effect == "landmark_offset":
        k = int(erng.integers(nl))
        d = erng.uniform(0.2, 0.5)
        ang = erng.uniform(-np.pi, np.pi)
        lm_true[k] += d * np.array([np.cos(ang), np.sin(ang)])
        eff.update(landmark=int(ids[k]), offset=[float(d * np.cos(ang)), float(d * np.sin(ang))],
                   distance=float(d))

    # ---------------- command times: 10 Hz with jitter, still increasing
    T = a.minutes * 60.0
    n_cmd = int(round(T * 10))
    jit = np.clip(nrng.normal(0, 0.003, n_cmd), -0.008, 0.008)
    tc = P["t0"] + np.arange(n_cmd) * 0.1 + jit
    tc = np.round(tc, 4)
    t_end = tc[-1] + 0.1

    # ---------------- simulate
    margin = 1.0
    def new_wp():
        return np.array([rng.uniform(x0 + margin, x0 + W - margin),
                         rng.uniform(y0 + margin, y0 + H - margin)])
    x = float(rng.uniform(x0 + margin, x0 + W - margin))
    y = float(rng.uniform(y0 + margin, y0 + H - margin))
    th = float(rng.uniform(-np.pi, np.pi))
    wp = new_wp()
    cruise = rng.uniform(0.15, 0.6)
    kw = rng.uniform(1.0, 3.0)
    mode, mode_until, mode_cmd = "drive", -1.0, (0.0, 0.0)
    wl = wr = 0.0             # actual wheel speeds
    sl = sr = 0.0             # slip states
    dt_sim = 0.005
    if a.no_slip:
        P["slip_sigma"] = 0.0
    a_ou = math.exp(-dt_sim / P["slip_corr_s"])
    b_ou = P["slip_sigma"] * math.sqrt(1 - a_ou * a_ou)
    rec_t, rec_x, rec_y, rec_th = [float(tc[0])], [x], [y], [th]
    cmds = np.zeros((n_cmd, 2))
    mode_rng = np.random.default_rng([a.seed, 31337])

    for k in range(n_cmd):
        t = tc[k]
        # controller (uses the true pose: a well-localised robot)
        if mode != "drive" and t >= mode_until:
            mode = "drive"
        if mode == "drive":
            r = mode_rng.uniform()
            if r < 0.004:
                mode, mode_until, mode_cmd = "stop", t + mode_rng.uniform(0.5, 2.0), (0.0, 0.0)
            elif r < 0.010:
                mode, mode_until = "spin", t + mode_rng.uniform(1.0, 3.0)
                mode_cmd = (0.0, float(mode_rng.choice([-1, 1]) * mode_rng.uniform(0.3, 1.5)))
            elif r < 0.014:
                mode, mode_until = "reverse", t + mode_rng.uniform(1.0, 2.0)
                mode_cmd = (float(-mode_rng.uniform(0.08, 0.2)), float(mode_rng.uniform(-0.4, 0.4)))
        if mode == "drive":
            dx, dy = wp[0] - x, wp[1] - y
            dist = math.hypot(dx, dy)
            if dist < 0.3:
                wp = new_wp()
                cruise = rng.uniform(0.15, 0.6)
                kw = rng.uniform(1.0, 3.0)
                dx, dy = wp[0] - x, wp[1] - y
                dist = math.hypot(dx, dy)
            err = math.atan2(dy, dx) - th
            err = (err + math.pi) % (2 * math.pi) - math.pi
            w = max(-1.5, min(1.5, kw * err))
            v = cruise * max(0.0, math.cos(err)) ** 2 * min(1.0, dist / 0.8)
            v = max(-0.2, min(0.6, v))
        else:
            v, w = mode_cmd
            # keep reversing from leaving the field
            if mode == "reverse" and not (x0 + 0.3 < x < x0 + W - 0.3 and y0 + 0.3 < y < y0 + H - 0.3):
                v, w = 0.0, 0.0
        v, w = round(v, 4), round(w, 4)
        cmds[k] = (v, w)
        t_next = tc[k + 1] if k + 1 < n_cmd else t_end
        # integrate at 200 Hz (the last sub-step shortened to land on t_next)
        tt = t
        while tt < t_next - 1e-9:
            h = min(dt_sim, t_next - tt)
            tl, tr = wheel_targets(v, w, tt, P, eff)
            al = 1.0 - math.exp(-h / P["tau"])
            wl += (tl - wl) * al
            wr += (tr - wr) * al
            sl = a_ou * sl + b_ou * nrng.standard_normal()
            sr = a_ou * sr + b_ou * nrng.standard_normal()
            kl, kr = 1.0 + sl, 1.0 + sr
            if on_carpet(x, y, eff):
                kl *= 1.0 - eff["extra_slip"]
                kr *= 1.0 - eff["extra_slip"]
            gl, gr = wl * kl, wr * kr
            vb = 0.5 * (gl + gr)
            wb = (gr - gl) / P["track"]
            thm = th + 0.5 * wb * h
            x += vb * h * math.cos(thm)
            y += vb * h * math.sin(thm)
            th += wb * h
            tt += h
            rec_t.append(tt); rec_x.append(x); rec_y.append(y); rec_th.append(th)

    rt = np.array(rec_t); rx = np.array(rec_x); ry = np.array(rec_y); rth = np.array(rec_th)

    def pose_at(tq):
        return (np.interp(tq, rt, rx), np.interp(tq, rt, ry), np.interp(tq, rt, rth))

    # ---------------- sensor on its own clock
    period = (1.0 / S["rate_hz"]) * (1.0 + S["clock_drift"])
    ts = P["t0"] + S["clock_offset"] + np.arange(0, int(T / period) + 1) * period
    ts = ts[ts < t_end - 0.05]
    lat = eff.get("latency_s", 0.0)
    px, py, pth = pose_at(ts - lat)
    obs = []
    for i, t in enumerate(ts):
        for j in range(nl):
            dxl, dyl = lm_true[j, 0] - px[i], lm_true[j, 1] - py[i]
            d = math.hypot(dxl, dyl)
            if d < S["min_range"] or d > S["max_range"]:
                continue
            if nrng.uniform() < S["dropout"]:
                continue
            brg = float(wrap(math.atan2(dyl, dxl) - pth[i]))
            if a.sensor == "range":
                rd = S["scale"] * d + S["bias"] + nrng.normal(0, S["reading_sigma"])
                bg = float(wrap(brg + nrng.normal(0, S["bearing_sigma"])))
            elif a.sensor == "rssi":
                rd = -10 * S["n"] * math.log10(d) + S["A"] + nrng.normal(0, S["reading_sigma"])
                bg = None
            else:
                rd = None
                bg = float(wrap(brg + nrng.normal(0, S["bearing_sigma"])))
            # sighting stamped with a tiny per-landmark processing offset (still the sensor clock)
            obs.append((round(t + 0.0005 * j, 4), int(ids[j]), rd, bg, d))
    obs.sort(key=lambda r: r[0])

    # ---------------- write
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "landmarks.csv"), "w") as f:
        f.write("landmark,x,y\n")
        for i in range(nl):
            f.write(f"{ids[i]},{lm[i,0]:.4f},{lm[i,1]:.4f}\n")
    with open(os.path.join(a.out, "commands.csv"), "w") as f:
        f.write("t,v,w\n")
        for k in range(n_cmd):
            f.write(f"{tc[k]:.4f},{cmds[k,0]:.4f},{cmds[k,1]:.4f}\n")
    fmt = lambda z, p: "" if z is None else f"{z:.{p}f}"
    with open(os.path.join(a.out, "observations.csv"), "w") as f:
        f.write("t,landmark,reading,bearing\n")
        for t, l, rd, bg, d in obs:
            f.write(f"{t:.4f},{l},{fmt(rd, 4)},{fmt(bg, 5)}\n")
    with open(os.path.join(a.out, "obs_truth.csv"), "w") as f:
        f.write("t,landmark,distance\n")
        for t, l, rd, bg, d in obs:
            f.write(f"{t:.4f},{l},{d:.4f}\n")
    tt = np.arange(tc[0], t_end, 0.02)
    qx, qy, qth = pose_at(tt)
    np.savetxt(os.path.join(a.out, "truth.csv"),
               np.column_stack([tt, qx, qy, wrap(qth)]), delimiter=",",
               header="t,x,y,theta", comments="", fmt="%.5f")
    # steady-state true velocity of each command (off-carpet, at the command's time) and the
    # velocity actually realised over the step (from truth, includes lag and slip)
    cx, cy, cth = pose_at(tc)
    with open(os.path.join(a.out, "cmd_truth.csv"), "w") as f:
        f.write("t,v,w,v_true,w_true,v_true_here\n")
        for k in range(n_cmd):
            vt, wt = steady_body(cmds[k, 0], cmds[k, 1], tc[k], P, eff)
            vh, _ = steady_body(cmds[k, 0], cmds[k, 1], tc[k], P, eff, cx[k], cy[k])
            f.write(f"{tc[k]:.4f},{cmds[k,0]:.4f},{cmds[k,1]:.4f},{vt:.5f},{wt:.5f},{vh:.5f}\n")
    wt_json = dict(seed=a.seed, minutes=a.minutes, field=[float(v) for v in field],
                   landmarks_map={int(i): [float(p[0]), float(p[1])] for i, p in zip(ids, lm)},
                   landmarks_true={int(i): [float(p[0]), float(p[1])] for i, p in zip(ids, lm_true)},
                   robot=P, firmware_track=B_NOMINAL, sensor=S, effect=eff,
                   linear_map_no_saturation={
                       "v_from_v": (P["gain_l"] + P["gain_r"]) / 2,
                       "v_from_w": (P["gain_r"] - P["gain_l"]) / 2 * B_NOMINAL / 2,
                       "w_from_v": (P["gain_r"] - P["gain_l"]) / P["track"],
                       "w_from_w": (P["gain_r"] + P["gain_l"]) / 2 * B_NOMINAL / P["track"]},
                   n_commands=n_cmd, n_observations=len(obs))
    with open(os.path.join(a.out, "world_truth.json"), "w") as f:
        json.dump(wt_json, f, indent=1)


if __name__ == "__main__":
    main()
