#!/usr/bin/env python3
"""Run casm-graph on tests/worlds/car_world.py's logs (a car-like robot, a lidar seeing poles) as a user
would, and score the fits against the truth.

python benchmarks/car_world.py [--out car_runs] [--minutes 6] [--calibrate-args ARGS] CASE...   CASE = effect:seed
e.g.  python benchmarks/car_world.py none:0 battery_fade:1 sideslip:0

Per case: generate the log, `calibrate`, `diagnose`; when the verdict names a catalog effect, calibrate again
with it (the `--effect` the diagnosis' summary says, else the verdict) and diagnose with `--before`; when it
is `unexplained:...` with a proposal, calibrate with `--effect proposal --proposal DIAG` and diagnose again.
Scores: position RMS of trajectory.csv against truth.csv; the speed and turn maps against cmd_truth.csv
(RMS, % of the true range); reading/bearing sigma fitted vs true; the sensor line against the true one.
One printed row per case, and OUT/results.jsonl (appended).  Only documented model.json /
diagnosis.json fields are read.  One casm-graph process at a time.
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
GENERATOR = os.path.join(os.path.dirname(HERE), "tests", "worlds", "car_world.py")
CASM = shutil.which("casm-graph") or "casm-graph"
TIMEOUT = 1800
CATALOG = {"actuator_lag", "battery_fade", "camera_latency", "false_detections", "landmark_offset",
           "lens_distortion", "range_dependent_noise", "surface_friction", "regional_motion_noise"}


def run(cmd, env):
    t0 = time.time()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT, env=env)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc = "timeout"
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        err = e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or "")
    return rc, out, err, time.time() - t0


def clean(text):
    lines = []
    for ln in (text or "").replace("\r", "\n").splitlines():
        s = ln.strip()
        if not s or "%|" in s or "it/s" in s or "s/it" in s:
            continue
        lines.append(s)
    return lines


def load_csv(p):
    return np.genfromtxt(p, delimiter=",", names=True, dtype=float)


def poly(coef, u):
    return sum(c * u ** i for i, c in enumerate(coef))


def effect_factors(model, ct):
    """Speed and turn factors the fitted motion effects apply at each command (time, true place), where the
    effect's documented form lets us compute them; None when not."""
    eff = model.get("effects") or {}
    fv = np.ones(len(ct)); fw = np.ones(len(ct)); used = []
    for name, p in eff.items():
        if name == "battery_fade":
            m = ct["t"] / 60.0
            f = 1 - p.get("loss_per_minute", 0.0) * m - p.get("loss_per_minute_squared", 0.0) * m ** 2
            fv *= f; fw *= f; used.append(name)
        elif name == "surface_friction":
            order = p.get("order")
            x, y = ct["x"], ct["y"]
            share = p.get("turn_share", 1.0)
            if order == 0:
                inside = (x >= p["west"]) & (x <= p["east"]) & (y >= p["south"]) & (y <= p["north"])
                s = p["slow"] * inside
            elif order is not None and order >= 2 and "extent" in p:
                K = int(order); x0, y0, x1, y1 = p["extent"]
                N = np.array([[p[f"slow_{i}_{j}"] for j in range(K)] for i in range(K)])
                u = np.clip((x - x0) / (x1 - x0) * (K - 1), 0, K - 1 - 1e-9)
                v = np.clip((y - y0) / (y1 - y0) * (K - 1), 0, K - 1 - 1e-9)
                i, j = u.astype(int), v.astype(int); a, b = u - i, v - j
                s = (N[i, j] * (1 - a) * (1 - b) + N[i + 1, j] * a * (1 - b) + N[i, j + 1] * (1 - a) * b
                     + N[i + 1, j + 1] * a * b)
            else:
                return None, None, "surface_friction order %s not scored" % order
            fv *= 1 - s; fw *= 1 - share * s; used.append(f"{name}:{order}")
        elif name in ("actuator_lag",):
            continue          # steady-state map unchanged
        elif name in ("proposal",):
            return None, None, "proposal terms not applied to the map score"
    return fv, fw, ",".join(used)


def map_scores(model, ct, world, prefix=""):
    out = {}
    am = model["action_model"]
    if am.get("kind") != "command_poly":
        out[prefix + "map_kind"] = am.get("kind")
        return out
    sv, sw = am["scale"]["v"], am["scale"]["w"]
    fv = poly(am["coefficients"]["v"], ct["v"] / sv)
    cross = (am.get("cross") or {}).get("w", {}).get("v")
    fw = poly(am["coefficients"]["w"], ct["w"] / sw) + (cross or 0.0) * ct["v"] / sv
    rv, rw = np.ptp(ct["v_true"]), np.ptp(ct["w_true"])
    e = lambda a, b, r: float(100 * np.sqrt(np.mean((a - b) ** 2)) / r)
    out[prefix + "speed_err_pct"] = e(fv, ct["v_true"], rv)          # the bare map vs the true effective map
    out[prefix + "turn_err_pct"] = e(fw, ct["w_true"], rw)
    out[prefix + "speed_err_noeffect_pct"] = e(fv, ct["v_true_noeffect"], rv)
    out[prefix + "turn_err_noeffect_pct"] = e(fw, ct["w_true_noeffect"], rw)
    kv, kw, used = effect_factors(model, ct)
    if kv is not None and used:
        out[prefix + "speed_err_with_effects_pct"] = e(fv * kv, ct["v_true"], rv)
        out[prefix + "turn_err_with_effects_pct"] = e(fw * kw, ct["w_true"], rw)
        out[prefix + "effects_in_map_score"] = used
    elif used:
        out[prefix + "effects_in_map_score"] = used
    out[prefix + "coef_v"] = [round(c / sv ** i, 4) for i, c in enumerate(am["coefficients"]["v"])]  # per m/s^i
    out[prefix + "coef_w"] = [round(c / sw ** i, 4) for i, c in enumerate(am["coefficients"]["w"])]
    out[prefix + "cross_w_per_v"] = None if cross is None else round(cross / sv, 4)
    out[prefix + "lag"] = am.get("lag"); out[prefix + "lag_order"] = am.get("lag_order")
    return out


def floors(ct):
    """The best the documented map class can do (LS: speed deg 2 in v; turn deg 1 in w plus a term in v), and the
    truth's turn term in w * v beyond that map (the form a proposal can write) with its share of the rest."""
    v, w = ct["v"], ct["w"]
    rv, rw = np.ptp(ct["v_true"]), np.ptp(ct["w_true"])
    Av = np.column_stack([v ** 0, v, v ** 2]); Aw = np.column_stack([w ** 0, w, v])
    bv = np.linalg.lstsq(Av, ct["v_true"], rcond=None)[0]; bw = np.linalg.lstsq(Aw, ct["w_true"], rcond=None)[0]
    ew = ct["w_true"] - Aw @ bw
    Ax = np.column_stack([Aw, w * v])
    bx = np.linalg.lstsq(Ax, ct["w_true"], rcond=None)[0]
    return {"speed_floor_pct": float(100 * np.sqrt(np.mean((Av @ bv - ct["v_true"]) ** 2)) / rv),
            "turn_floor_pct": float(100 * np.sqrt(np.mean(ew ** 2)) / rw),
            "true_v_range": float(rv), "true_w_range": float(rw),
            # the truth's turn beyond the map, as a term w * v (the form the proposal library can write)
            "true_turn_w_speed": float(bx[-1]),
            "true_turn_w_speed_share": float(1.0 - np.var(ct["w_true"] - Ax @ bx) / np.var(ew))}


def score(log, runp, world, prefix=""):
    out = {}
    tr = load_csv(os.path.join(log, "truth.csv"))
    tj = load_csv(os.path.join(runp, "trajectory.csv"))
    xt = np.interp(tj["t"], tr["t"], tr["x"]); yt = np.interp(tj["t"], tr["t"], tr["y"])
    tht = np.interp(tj["t"], tr["t"], np.unwrap(tr["theta"]))
    e = np.hypot(tj["x"] - xt, tj["y"] - yt)
    out[prefix + "pos_rms"] = float(np.sqrt(np.mean(e ** 2)))
    out[prefix + "pos_max"] = float(e.max())
    dth = (tj["theta"] - tht + np.pi) % (2 * np.pi) - np.pi
    out[prefix + "head_rms_deg"] = float(np.degrees(np.sqrt(np.mean(dth ** 2))))
    m = json.load(open(os.path.join(runp, "model.json")))
    ct = load_csv(os.path.join(log, "cmd_truth.csv"))
    out.update(map_scores(m, ct, world, prefix))
    sm = m["sensor_model"]; S = world["sensor"]
    out[prefix + "reading_sigma"] = [sm.get("reading_sigma"), S["reading_sigma"]]
    out[prefix + "bearing_sigma"] = [sm.get("bearing_sigma"), S["bearing_sigma"]]
    if sm.get("reading_poly") is not None:
        ot = load_csv(os.path.join(log, "obs_truth.csv"))
        d = ot["distance"]
        u = d if sm.get("reading_basis", "distance") == "distance" else 1.0 / d
        err = poly(sm["reading_poly"], u) - (S["scale"] * d + S["bias"])
        out[prefix + "reading_poly"] = [round(c, 5) for c in sm["reading_poly"]]
        out[prefix + "sensor_curve_rms"] = float(np.sqrt(np.mean(err ** 2)))
    out[prefix + "motion_noise"] = m.get("motion_noise")
    out[prefix + "effects"] = m.get("effects")
    fit = m.get("fit", {})
    out[prefix + "effects_std"] = fit.get("effects_std")
    for k in ("converged", "iterations", "outliers_set_aside", "sensor_degree", "log_likelihood", "seconds"):
        out[prefix + "fit_" + k] = fit.get(k)
    return out


def diag_summary(diag, prefix=""):
    d = json.load(open(os.path.join(diag, "diagnosis.json")))
    r = {prefix + "verdict": d.get("verdict"),
         prefix + "summary": d.get("summary", []),
         prefix + "candidates": [{k: c.get(k) for k in ("effect", "channel", "delta_bic", "heldout_nll_drop",
                                                        "order", "parameters", "implausible")}
                                 for c in d.get("candidates", [])[:6]],
         prefix + "lookalikes": [l.get("effects") for l in d.get("lookalikes", [])],
         prefix + "top_covariates": {ch: [(c["name"], round(c["strength"], 4), c.get("kind"),
                                           float("%.3g" % c["p"]) if c.get("p") is not None else None)
                                          for c in v.get("covariates", [])[:3]]
                                     for ch, v in d.get("channels", {}).items()},
         prefix + "channel_rms": {ch: v.get("rms") for ch, v in d.get("channels", {}).items()},
         prefix + "sightings_set_aside": d.get("sightings_set_aside"),
         prefix + "not_applicable": d.get("not_applicable")}
    if d.get("proposal"):
        r[prefix + "proposal_equation"] = d["proposal"].get("equation")
        r[prefix + "proposal_fitted"] = d["proposal"].get("fitted")
    if d.get("before_after"):
        ba = d["before_after"]
        r[prefix + "before_after"] = {"verdict": ba.get("verdict"), "log_likelihood": ba.get("log_likelihood"),
                                      "rms": {ch: v.get("rms") for ch, v in ba.get("channels", {}).items()}}
    return d, r


def add_effect_args(d):
    """The --effect argument to add the diagnosis' verdict: what its summary says to add, else the verdict."""
    v = d.get("verdict") or ""
    for line in d.get("summary", []):
        for m in re.finditer(r"--effect\s+([A-Za-z_]+(?::\d+)?)", line):
            if m.group(1).split(":")[0] == v:
                return m.group(1)
    return v


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--out", default="car_runs")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--strength", type=float, default=None)
    ap.add_argument("--tag", default="", help="suffix of the case directory")
    ap.add_argument("--gen-args", default="", help="extra car_world.py arguments, e.g. '--set car.motor_tau=0.001'")
    ap.add_argument("--calibrate-args", default="", help="extra arguments of both calibrations, e.g. "
                                                         "'--step-heading middle'")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    res_path = os.path.join(a.out, "results.jsonl")
    for case in a.cases:
        effect, seed = case.split(":")
        name = f"{effect}_s{seed}_{a.minutes:g}min{a.tag}"
        base = os.path.join(a.out, name)
        if os.path.exists(base):
            shutil.rmtree(base)
        log, runp, diag, run2, diag2 = (os.path.join(base, x) for x in ("log", "run", "diag", "run2", "diag2"))
        rec = {"case": name, "effect": effect, "seed": int(seed), "minutes": a.minutes}
        t0 = time.time()
        gen = [sys.executable, GENERATOR, log, "--minutes", str(a.minutes), "--seed", seed, "--effect", effect]
        if a.strength is not None:
            gen += ["--strength", str(a.strength)]
        gen += a.gen_args.split()
        rec["gen_args"] = a.gen_args
        subprocess.run(gen, check=True, env=env)
        world = json.load(open(os.path.join(log, "world_truth.json")))
        rec["world_effect"] = world["effect"]
        rec["world_car"] = {k: world["car"][k] for k in ("wheelbase", "wheelbase_nominal", "trim_deg", "motor_gain",
                                                         "motor_offset", "vmax", "delta_max_deg")}
        rec["world_sensor"] = {k: world["sensor"][k] for k in ("scale", "bias", "reading_sigma", "bearing_sigma",
                                                               "max_range", "rate_hz")}
        rec["n_obs"], rec["n_cmd"] = world["n_observations"], world["n_commands"]
        rec["linear_map"] = world["linear_map_no_saturation"]
        rec.update(floors(load_csv(os.path.join(log, "cmd_truth.csv"))))
        steps = []
        cmd = [CASM, "calibrate", log, "--out", runp, "--quiet"] + a.calibrate_args.split()
        rec["calibrate_args"] = a.calibrate_args
        rc, out, err, sec = run(cmd, env)
        steps.append({"cmd": " ".join(cmd), "rc": rc, "s": round(sec, 1), "stderr": clean(err), "stdout": clean(out)[-6:]})
        if rc == 0:
            rec.update(score(log, runp, world))
            cmd = [CASM, "diagnose", log, "--model", os.path.join(runp, "model.json"), "--out", diag,
                   "--workers", "1", "--quiet"]
            rc, out, err, sec = run(cmd, env)
            steps.append({"cmd": " ".join(cmd), "rc": rc, "s": round(sec, 1), "stderr": clean(err),
                          "stdout": clean(out)[-8:]})
            if rc == 0:
                d, r = diag_summary(diag)
                rec.update(r)
                v = d.get("verdict") or ""
                add = None
                if v in CATALOG:
                    add = ["--effect", add_effect_args(d)]
                elif v.startswith("unexplained:") and d.get("proposal"):
                    add = ["--effect", "proposal", "--proposal", diag]
                if add:
                    rec["added"] = " ".join(add)
                    cmd = [CASM, "calibrate", log, "--out", run2, "--quiet"] + a.calibrate_args.split() + add
                    rc, out, err, sec = run(cmd, env)
                    steps.append({"cmd": " ".join(cmd), "rc": rc, "s": round(sec, 1), "stderr": clean(err),
                                  "stdout": clean(out)[-6:]})
                    if rc == 0:
                        rec.update(score(log, run2, world, prefix="r2_"))
                        cmd = [CASM, "diagnose", log, "--model", os.path.join(run2, "model.json"), "--out", diag2,
                               "--workers", "1", "--quiet", "--before", diag]
                        rc, out, err, sec = run(cmd, env)
                        steps.append({"cmd": " ".join(cmd), "rc": rc, "s": round(sec, 1), "stderr": clean(err),
                                      "stdout": clean(out)[-8:]})
                        if rc == 0:
                            rec.update(diag_summary(diag2, prefix="r2_")[1])
        rec["steps"] = steps
        rec["seconds"] = round(time.time() - t0, 1)
        with open(res_path, "a") as f:
            f.write(json.dumps(rec, default=float) + "\n")
        g = lambda k, p=3: "-" if rec.get(k) is None else (f"{rec[k]:.{p}f}" if isinstance(rec[k], float) else str(rec[k]))
        fs = lambda z: "-" if z is None else f"{z:.3g}"
        rs, bs = rec.get("reading_sigma", [None, None]), rec.get("bearing_sigma", [None, None])
        print(f"{name:26s} verdict={rec.get('verdict','-')} look={rec.get('lookalikes') or '-'} "
              f"-> {rec.get('r2_verdict','-')} pos={g('pos_rms')}->{g('r2_pos_rms')}m "
              f"speed={g('speed_err_pct',1)}% turn={g('turn_err_pct',1)}% (floor {g('speed_floor_pct',1)}/"
              f"{g('turn_floor_pct',1)}) rsig={fs(rs[0])}/{fs(rs[1])} bsig={fs(bs[0])}/{fs(bs[1])} "
              f"rc={[s['rc'] for s in steps]} {rec['seconds']:.0f}s", flush=True)
        for s in steps:
            if s["rc"] != 0 or s["stderr"]:
                print("    ", s["cmd"].split()[1], "rc", s["rc"], "stderr:", s["stderr"][:3], flush=True)


if __name__ == "__main__":
    main()
