#!/usr/bin/env python3
"""A car-like robot (kinematic bicycle / Ackermann) in an outdoor lot, with a 2-D lidar seeing poles.

Standalone log generator (numpy only), written from the user documentation (docs/log-format.md) alone.

    python car_world.py OUT --minutes M --seed S --effect NAME [--strength X]

NAME: none, battery_fade, surface_friction, actuator_lag, camera_latency, landmark_offset (the library's
catalog) and sideslip, understeer (not in it).  --strength X sets the effect's size in its own unit:
battery_fade loss per minute; surface_friction share of speed lost on the patch; actuator_lag extra mean
delay (s); camera_latency delay (s); landmark_offset metres; sideslip k (s); understeer share of yaw rate
lost at top speed.

Writes OUT/landmarks.csv, OUT/commands.csv (t,v,w), OUT/observations.csv (t,landmark,reading,bearing)
and, for scoring only, OUT/truth.csv (t,x,y,theta at 50 Hz), OUT/cmd_truth.csv (per logged command: the
true steady-state forward speed and yaw rate it produces at that time and place), OUT/obs_truth.csv (the
true distance of each sighting) and OUT/world_truth.json (every drawn parameter).
"""
import argparse
import json
import math
import os

import numpy as np

EFFECTS = ("none", "battery_fade", "surface_friction", "actuator_lag", "camera_latency", "landmark_offset",
           "sideslip", "understeer")
FS = 400.0                 # integration rate, Hz
TRUTH_HZ = 50.0
V_STOP = 0.02              # set-points below this park the car
EPS_V = 0.1                # firmware: delta = atan(w L_nom / max(v, EPS_V))


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def draw_world(seed, effect, strength, minutes):
    rw = np.random.default_rng([seed, 11])      # the world: same for every effect at one seed
    re = np.random.default_rng([seed, 22])      # the effect's strength and geometry
    W = {"seed": seed, "minutes": minutes}
    # ---- lot -------------------------------------------------------------------------------
    sx, sy = rw.uniform(15, 40, size=2)
    cx = rw.choice([-1, 1]) * rw.uniform(6, 30)
    cy = rw.choice([-1, 1]) * rw.uniform(6, 30)
    lot = [cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2]
    W["lot"] = {"extent": [round(v, 4) for v in lot], "size": [sx, sy], "centre": [cx, cy]}
    margin = 2.5
    W["waypoint_box"] = [lot[0] + margin, lot[1] + margin, lot[2] - margin, lot[3] - margin]
    # ---- landmarks --------------------------------------------------------------------------
    n_lm = int(rw.integers(6, 13))
    pts = []
    while len(pts) < n_lm:
        p = np.array([rw.uniform(lot[0] - 1, lot[2] + 1), rw.uniform(lot[1] - 1, lot[3] + 1)])
        if all(np.hypot(*(p - q)) > 3.0 for q in pts):
            pts.append(p)
    ids = sorted(rw.choice(np.arange(1, 60), size=n_lm, replace=False).tolist())
    W["landmarks_true"] = {int(i): [float(p[0]), float(p[1])] for i, p in zip(ids, pts)}
    # ---- car ----------------------------------------------------------------------------------
    L = rw.uniform(0.3, 0.6)
    car = {
        "wheelbase": L,
        "wheelbase_nominal": L * (1 + rw.choice([-1, 1]) * rw.uniform(0.02, 0.06)),
        "delta_max_deg": rw.uniform(25, 35),
        "trim_deg": rw.choice([-1, 1]) * rw.uniform(0.5, 2.0),
        "motor_gain": rw.uniform(0.9, 1.1),
        "motor_offset": rw.uniform(-0.03, 0.03),
        "motor_tau": rw.uniform(0.04, 0.07),
        "steer_tau": rw.uniform(0.02, 0.04),
        "vmax": rw.uniform(1.8, 2.3),
        "slip_v_std": rw.uniform(0.02, 0.04),
        "slip_w_std": rw.uniform(0.008, 0.015),
        "slip_tau": rw.uniform(0.25, 0.4),
        "cmd_hz": rw.uniform(10, 20),
        "cmd_jitter_s": 0.003,
    }
    W["car"] = car
    # ---- lidar --------------------------------------------------------------------------------
    W["sensor"] = {
        "kind": "range", "rate_hz": rw.uniform(9.5, 10.5), "phase_s": rw.uniform(0, 0.1), "jitter_s": 0.001,
        "fov_deg": 270.0, "max_range": rw.uniform(15, 25), "min_range": 0.3, "dropout": rw.uniform(0.02, 0.05),
        "scale": rw.uniform(1.0, 1.03), "bias": rw.uniform(0.0, 0.1),
        "reading_sigma": rw.uniform(0.03, 0.08), "bearing_sigma": rw.uniform(0.005, 0.02),
    }
    # ---- planner ------------------------------------------------------------------------------
    W["planner"] = {"v_leg": [0.5, 2.0], "accel": 1.2, "decel": 2.0, "a_lat_max": 2.0, "stop_prob": 0.2,
                    "stop_s": [1.0, 3.0], "reach_m": 1.2, "leg_timeout_s": 40.0}
    # ---- effect -------------------------------------------------------------------------------
    E = {"name": effect}
    if effect == "battery_fade":
        E["loss_per_minute"] = strength if strength is not None else re.uniform(0.01, 0.03)
        E["what"] = "motor gain and top speed scale by 1 - loss_per_minute * minutes"
    elif effect == "surface_friction":
        E["slow"] = strength if strength is not None else re.uniform(0.15, 0.30)
        E["target_area_share"] = re.uniform(0.15, 0.35)
        bx = W["waypoint_box"]
        E["centre"] = [re.uniform(bx[0] + 0.2 * (bx[2] - bx[0]), bx[2] - 0.2 * (bx[2] - bx[0])),
                       re.uniform(bx[1] + 0.2 * (bx[3] - bx[1]), bx[3] - 0.2 * (bx[3] - bx[1]))]
        E["aspect"] = re.uniform(1.0, 2.5)
        E["angle"] = re.uniform(0, np.pi)
        # size the ellipse so that it covers target_area_share of the waypoint box
        gx, gy = np.meshgrid(np.linspace(bx[0], bx[2], 240), np.linspace(bx[1], bx[3], 240))
        lo, hi = 0.1, 60.0
        for _ in range(60):
            a = 0.5 * (lo + hi)
            E["semi_axes"] = [a, a / E["aspect"]]
            share = float(np.mean(in_patch(E, gx, gy)))
            lo, hi = (a, hi) if share < E["target_area_share"] else (lo, a)
        E["area_share_of_waypoint_box"] = share
        E["what"] = "inside an ellipse (gravel) the motor reaches 1 - slow of its speed; yaw follows real speed"
    elif effect == "actuator_lag":
        E["tau"] = strength if strength is not None else re.uniform(0.15, 0.35)
        E["order"] = int(re.integers(1, 3))
        E["stage_tau"] = E["tau"] / E["order"]
        E["what"] = "speed set-point and steering command pass through `order` extra first-order stages of " \
                    "stage_tau each (mean delay tau), on top of the motor's and servo's own"
    elif effect == "camera_latency":
        E["delay"] = strength if strength is not None else re.uniform(0.05, 0.15)
        E["what"] = "each lidar sighting is taken at t - delay and logged at t"
    elif effect == "landmark_offset":
        E["distance"] = strength if strength is not None else re.uniform(0.3, 0.8)
        E["landmark"] = int(re.choice(ids))
        ang = re.uniform(-np.pi, np.pi)
        E["dx"], E["dy"] = E["distance"] * math.cos(ang), E["distance"] * math.sin(ang)
        E["what"] = "the pole stands at its map entry + (dx, dy)"
    elif effect == "sideslip":
        E["k"] = strength if strength is not None else re.uniform(0.03, 0.1)
        E["what"] = "lateral body velocity = -k v w (slides outwards in turns)"
    elif effect == "understeer":
        E["yaw_loss_at_top_speed"] = strength if strength is not None else re.uniform(0.10, 0.25)
        E["top_speed"] = car["vmax"]
        E["K"] = (1.0 / (1.0 - E["yaw_loss_at_top_speed"]) - 1.0) / car["vmax"] ** 2
        E["what"] = "yaw rate = v tan(delta) / (L (1 + K v^2))"
    W["effect"] = E
    W["landmarks_map"] = {i: list(p) for i, p in W["landmarks_true"].items()}
    if effect == "landmark_offset":
        i = E["landmark"]
        W["landmarks_map"][i] = [W["landmarks_true"][i][0] - E["dx"], W["landmarks_true"][i][1] - E["dy"]]
    return W


def in_patch(E, x, y):
    c, s = math.cos(E["angle"]), math.sin(E["angle"])
    dx, dy = np.asarray(x) - E["centre"][0], np.asarray(y) - E["centre"][1]
    u, v = c * dx + s * dy, -s * dx + c * dy
    return (u / E["semi_axes"][0]) ** 2 + (v / E["semi_axes"][1]) ** 2 <= 1.0


def motor_target(W, vc, t, x, y, with_effects=True):
    """Steady-state speed of set-point vc at time t and place (x, y)."""
    car, E = W["car"], W["effect"]
    if vc < V_STOP:
        return 0.0
    g, vmax = car["motor_gain"], car["vmax"]
    if with_effects and E["name"] == "battery_fade":
        f = max(0.0, 1.0 - E["loss_per_minute"] * t / 60.0)
        g, vmax = g * f, vmax * f
    v = min(max(g * vc + car["motor_offset"], 0.0), vmax)
    if with_effects and E["name"] == "surface_friction" and in_patch(E, x, y):
        v *= 1.0 - E["slow"]
    return v


def firmware_delta(W, vc, wc):
    car = W["car"]
    dmax = math.radians(car["delta_max_deg"])
    d = math.atan(wc * car["wheelbase_nominal"] / max(vc, EPS_V))
    return min(max(d, -dmax), dmax)


def yaw_of(W, v, delta):
    car, E = W["car"], W["effect"]
    w = v * math.tan(delta) / car["wheelbase"]
    if E["name"] == "understeer":
        w /= 1.0 + E["K"] * v * v
    return w


def simulate(W):
    car, E, P = W["car"], W["effect"], W["planner"]
    rn = np.random.default_rng([W["seed"], 33])     # process noise and planner choices
    T = W["minutes"] * 60.0
    dt = 1.0 / FS
    n = int(round(T * FS)) + 1
    # command tick times: nominal period with a few ms of jitter
    Tc = 1.0 / car["cmd_hz"]
    k = np.arange(int(T / Tc) + 1)
    tick = k * Tc + rn.uniform(-car["cmd_jitter_s"], car["cmd_jitter_s"], size=k.size)
    tick[0] = 0.0
    tick = tick[tick <= T - 0.05]
    box = W["waypoint_box"]
    poles = np.array(list(W["landmarks_true"].values()))

    def new_wp(cur):
        for _ in range(1000):
            p = np.array([rn.uniform(box[0], box[2]), rn.uniform(box[1], box[3])])
            if np.hypot(*(p - cur)) > 5.0 and np.min(np.hypot(*(poles - p).T)) > 1.5:
                return p
        return p

    # state
    x, y = rn.uniform(box[0], box[2]), rn.uniform(box[1], box[3])
    th = rn.uniform(-np.pi, np.pi)
    vm, ds = 0.0, math.radians(car["trim_deg"])
    sv = sw = 0.0
    lag_order = E.get("order", 0) if E["name"] == "actuator_lag" else 0
    lag_v = [0.0] * lag_order
    lag_d = [0.0] * lag_order
    a_lag = math.exp(-dt / E["stage_tau"]) if lag_order else 0.0
    a_m = math.exp(-dt / car["motor_tau"])
    a_s = math.exp(-dt / car["steer_tau"])
    a_ou = math.exp(-dt / car["slip_tau"])
    b_v = car["slip_v_std"] * math.sqrt(1 - a_ou ** 2)
    b_w = car["slip_w_std"] * math.sqrt(1 - a_ou ** 2)
    trim = math.radians(car["trim_deg"])
    wp = new_wp(np.array([x, y]))
    leg_v = rn.uniform(*P["v_leg"])
    leg_t0 = 0.0
    stop_here = rn.random() < P["stop_prob"]
    stop_until = -1.0
    vc = wc = 0.0
    delta_c = 0.0
    turn_dir = 1
    kappa_max = min(0.8, 0.85 * math.tan(math.radians(car["delta_max_deg"])) / car["wheelbase_nominal"])
    noise = rn.standard_normal((n, 2))
    ts = np.arange(n) * dt
    X = np.empty((n, 6))     # x, y, theta (unwrapped), v_true, w_true, lateral
    cmds = []                # (t, v, w, x, y, theta, delta_cmd)
    ci = 0
    for i in range(n):
        t = ts[i]
        # ---- planner tick --------------------------------------------------------------------
        while ci < tick.size and tick[ci] <= t + 1e-12:
            tk = tick[ci]
            ci += 1
            dxw, dyw = wp[0] - x, wp[1] - y
            dist = math.hypot(dxw, dyw)
            if tk < stop_until:
                vdes, kap = 0.0, 0.0
            else:
                alpha = wrap(math.atan2(dyw, dxw) - th)
                orbit = dist < 2.5 / kappa_max and abs(alpha) > 1.2      # inside the turning circle: give up
                if dist < P["reach_m"] or orbit or tk - leg_t0 > P["leg_timeout_s"]:
                    if stop_here:
                        stop_until = tk + rn.uniform(*P["stop_s"])
                    wp = new_wp(np.array([x, y]))
                    leg_v = rn.uniform(*P["v_leg"])
                    leg_t0 = tk
                    stop_here = rn.random() < P["stop_prob"]
                    turn_dir = 1 if rn.random() < 0.5 else -1
                    dxw, dyw = wp[0] - x, wp[1] - y
                    dist = math.hypot(dxw, dyw)
                if tk < stop_until:
                    vdes, kap = 0.0, 0.0
                else:
                    alpha = wrap(math.atan2(dyw, dxw) - th)
                    ld = min(max(dist, 2.0), 6.0)                  # pure pursuit, look-ahead 2-6 m
                    if abs(alpha) <= np.pi / 2:
                        kap = 2.0 * math.sin(alpha) / ld
                    elif abs(alpha) > 2.0:                          # target behind: turn to this leg's side
                        kap = turn_dir * 2.0 / ld
                    else:
                        kap = math.copysign(2.0 / ld, alpha)
                    kap = min(max(kap, -kappa_max), kappa_max)
                    vdes = leg_v * max(0.5, math.cos(alpha))
                    vdes = min(vdes, math.sqrt(P["a_lat_max"] / max(abs(kap), 1e-6)))
                    if stop_here:
                        vdes = min(vdes, math.sqrt(2 * 0.8 * max(dist - 0.8, 0.0)) + 0.3)
                    vdes = max(vdes, 0.3)
            dtc = Tc
            vnew = min(max(vdes, vc - P["decel"] * dtc), vc + P["accel"] * dtc)
            if vdes == 0.0 and vnew < 0.25:
                vnew = 0.0
            vc = vnew
            wc = vc * kap if vc > 0 else 0.0
            delta_c = firmware_delta(W, vc, wc)
            cmds.append((tk, vc, wc, x, y, th, delta_c))
        # ---- actuators -----------------------------------------------------------------------
        uv, ud = vc, delta_c
        for s in range(lag_order):
            lag_v[s] = a_lag * lag_v[s] + (1 - a_lag) * uv
            lag_d[s] = a_lag * lag_d[s] + (1 - a_lag) * ud
            uv, ud = lag_v[s], lag_d[s]
        vt = motor_target(W, uv, t, x, y)
        vm = a_m * vm + (1 - a_m) * vt
        ds = a_s * ds + (1 - a_s) * (ud + trim)
        sv = a_ou * sv + b_v * noise[i, 0]
        sw = a_ou * sw + b_w * noise[i, 1]
        v = max(vm * (1 + sv), 0.0)
        w = yaw_of(W, v, ds) * (1 + sw)
        lat = -E["k"] * v * w if E["name"] == "sideslip" else 0.0
        X[i] = (x, y, th, v, w, lat)
        # ---- integrate (midpoint heading) ----------------------------------------------------
        thm = th + 0.5 * w * dt
        c, s_ = math.cos(thm), math.sin(thm)
        x += (v * c - lat * s_) * dt
        y += (v * s_ + lat * c) * dt
        th += w * dt
    return ts, X, np.array(cmds)


def lidar(W, ts, X):
    S, E = W["sensor"], W["effect"]
    rs = np.random.default_rng([W["seed"], 44])
    T = ts[-1]
    per = 1.0 / S["rate_hz"]
    tk = S["phase_s"] + 0.05 + np.arange(int(T / per) + 1) * per
    tk = tk + rs.uniform(-S["jitter_s"], S["jitter_s"], size=tk.size)
    tk = tk[(tk > 0.05) & (tk < T - 0.3)]
    delay = E["delay"] if E["name"] == "camera_latency" else 0.0
    ttake = tk - delay
    ok = ttake >= 0
    tk, ttake = tk[ok], ttake[ok]
    px = np.interp(ttake, ts, X[:, 0])
    py = np.interp(ttake, ts, X[:, 1])
    pth = np.interp(ttake, ts, X[:, 2])
    rows, truth = [], []
    half = math.radians(S["fov_deg"]) / 2
    for lid, (lx, ly) in W["landmarks_true"].items():
        d = np.hypot(lx - px, ly - py)
        b = wrap(np.arctan2(ly - py, lx - px) - pth)
        vis = (d <= S["max_range"]) & (d >= S["min_range"]) & (np.abs(b) <= half)
        vis &= rs.random(d.size) >= S["dropout"]
        idx = np.nonzero(vis)[0]
        r = S["scale"] * d[idx] + S["bias"] + S["reading_sigma"] * rs.standard_normal(idx.size)
        bb = wrap(b[idx] + S["bearing_sigma"] * rs.standard_normal(idx.size))
        for j, k in enumerate(idx):
            rows.append((tk[k], lid, r[j], bb[j]))
            truth.append((tk[k], lid, d[k], b[k], ttake[k]))
    order = np.lexsort((np.array([r_[1] for r_ in rows]), np.array([r_[0] for r_ in rows])))
    return [rows[i] for i in order], [truth[i] for i in order]


def cmd_truth(W, cmds):
    car, E = W["car"], W["effect"]
    trim = math.radians(car["trim_deg"])
    out = []
    for (t, v, w, x, y, th, dc) in cmds:
        v1 = motor_target(W, v, t, x, y, True)
        v0 = motor_target(W, v, t, x, y, False)
        w1, w0 = yaw_of(W, v1, dc + trim), yaw_of(W, v0, dc + trim)
        lat = -E["k"] * v1 * w1 if E["name"] == "sideslip" else 0.0
        inp = int(bool(in_patch(E, x, y))) if E["name"] == "surface_friction" else 0
        out.append((t, v, w, v1, w1, v0, w0, lat, inp, x, y))
    return np.array(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", default="none", choices=EFFECTS)
    ap.add_argument("--strength", type=float, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a drawn parameter after drawing (investigation only), e.g. car.motor_tau=0.001")
    a = ap.parse_args()
    W = draw_world(a.seed, a.effect, a.strength, a.minutes)
    for kv in a.set:
        k, v = kv.split("=", 1)
        sec, key = k.split(".", 1)
        if key not in W[sec]:
            raise SystemExit(f"--set: no parameter {k}")
        W[sec][key] = float(v)
    W["overrides"] = a.set
    ts, X, cmds = simulate(W)
    obs, obs_t = lidar(W, ts, X)
    ct = cmd_truth(W, cmds)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "landmarks.csv"), "w") as f:
        f.write("landmark,x,y\n")
        for i, (x, y) in sorted(W["landmarks_map"].items()):
            f.write(f"{i},{x:.4f},{y:.4f}\n")
    with open(os.path.join(a.out, "commands.csv"), "w") as f:
        f.write("t,v,w\n")
        for r in cmds:
            f.write(f"{r[0]:.4f},{r[1]:.4f},{r[2]:.4f}\n")
    with open(os.path.join(a.out, "observations.csv"), "w") as f:
        f.write("t,landmark,reading,bearing\n")
        for (t, lid, r, b) in obs:
            f.write(f"{t:.4f},{lid},{r:.4f},{b:.5f}\n")
    step = int(round(FS / TRUTH_HZ))
    with open(os.path.join(a.out, "truth.csv"), "w") as f:
        f.write("t,x,y,theta,v,w,lateral\n")
        for i in range(0, ts.size, step):
            x, y, th, v, w, lat = X[i]
            f.write(f"{ts[i]:.4f},{x:.5f},{y:.5f},{wrap(th):.6f},{v:.5f},{w:.5f},{lat:.5f}\n")
    with open(os.path.join(a.out, "cmd_truth.csv"), "w") as f:
        f.write("t,v,w,v_true,w_true,v_true_noeffect,w_true_noeffect,lateral_true,in_patch,x,y\n")
        for r in ct:
            f.write(",".join(f"{z:.6f}" for z in r[:8]) + f",{int(r[8])},{r[9]:.4f},{r[10]:.4f}\n")
    with open(os.path.join(a.out, "obs_truth.csv"), "w") as f:
        f.write("t,landmark,distance,bearing,t_taken\n")
        for (t, lid, d, b, tt) in obs_t:
            f.write(f"{t:.4f},{lid},{d:.5f},{b:.6f},{tt:.5f}\n")
    car = W["car"]
    g = car["motor_gain"]
    W["linear_map_no_saturation"] = {
        "v_from_v": g, "v_offset": car["motor_offset"],
        "w_from_w": g * car["wheelbase_nominal"] / car["wheelbase"],
        "w_from_v": g * math.tan(math.radians(car["trim_deg"])) / car["wheelbase"],
        "note": "small-signal: v_true ~ g v + offset; w_true ~ g (L_nom/L) w + g tan(trim)/L v"}
    W["n_observations"] = len(obs)
    W["n_commands"] = int(len(cmds))
    W["duration_s"] = float(ts[-1])
    W["commanded_v_range"] = [float(ct[:, 1].min()), float(ct[:, 1].max())]
    W["commanded_w_range"] = [float(ct[:, 2].min()), float(ct[:, 2].max())]
    W["visited_box"] = [float(X[:, 0].min()), float(X[:, 1].min()), float(X[:, 0].max()), float(X[:, 1].max())]
    W["share_of_steps_steering_clipped"] = float(np.mean(
        np.abs(cmds[:, 6]) >= math.radians(car["delta_max_deg"]) - 1e-9))
    if W["effect"]["name"] == "surface_friction":
        W["effect"]["share_of_time_on_patch"] = float(np.mean(in_patch(W["effect"], X[:, 0], X[:, 1])))
    W["landmarks_true"] = {str(k): v for k, v in W["landmarks_true"].items()}
    W["landmarks_map"] = {str(k): v for k, v in W["landmarks_map"].items()}
    with open(os.path.join(a.out, "world_truth.json"), "w") as f:
        json.dump(W, f, indent=1, default=float)


if __name__ == "__main__":
    main()
