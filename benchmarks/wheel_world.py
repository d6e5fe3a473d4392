#!/usr/bin/env python3
"""Run casm-graph calibrate + diagnose on tests/worlds/wheel_world.py's logs and score them against the truth.

python benchmarks/wheel_world.py [--out wheel_runs] [--minutes 6] [--workers 1] CASE...   CASE = sensor:effect:seed
e.g.  python benchmarks/wheel_world.py range:none:0 range:battery_fade:0 rssi:none:1
Results: one printed row per log and OUT/results.jsonl (appended).
Uses only the documented model.json fields (command_poly coefficients/scale, reading_poly,
reading_basis, sigmas) and trajectory.csv.
"""
import argparse
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
GENERATOR = os.path.join(os.path.dirname(HERE), "tests", "worlds", "wheel_world.py")
CASM = shutil.which("casm-graph") or "casm-graph"
TIMEOUT = 600


def run(cmd, env):
    t0 = time.time()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT, env=env)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, err = "timeout", (e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or ""))
    return rc, err, time.time() - t0


def clean_stderr(err):
    # drop progress-bar noise; keep warnings / errors / tracebacks
    lines = []
    for ln in err.replace("\r", "\n").splitlines():
        s = ln.strip()
        if not s or "%|" in s or "it/s" in s or "s/it" in s:
            continue
        lines.append(s)
    return lines


def load_csv(p):
    return np.genfromtxt(p, delimiter=",", names=True, dtype=float)


def poly_eval(coef, u):
    return sum(c * u ** i for i, c in enumerate(coef))


def lin_of(world):
    return world["linear_map_no_saturation"]


def score(log, runp, world):
    out = {}
    tr = load_csv(os.path.join(log, "truth.csv"))
    tj = load_csv(os.path.join(runp, "trajectory.csv"))
    xt = np.interp(tj["t"], tr["t"], tr["x"])
    yt = np.interp(tj["t"], tr["t"], tr["y"])
    tht = np.interp(tj["t"], tr["t"], np.unwrap(tr["theta"]))
    e = np.hypot(tj["x"] - xt, tj["y"] - yt)
    out["pos_rms"] = float(np.sqrt(np.mean(e ** 2)))
    out["pos_max"] = float(e.max())
    dth = (tj["theta"] - tht + np.pi) % (2 * np.pi) - np.pi
    out["head_rms_deg"] = float(np.degrees(np.sqrt(np.mean(dth ** 2))))
    m = json.load(open(os.path.join(runp, "model.json")))
    am = m["action_model"]
    out["action_kind"] = am.get("kind")
    ct = load_csv(os.path.join(log, "cmd_truth.csv"))
    if am.get("kind") == "command_poly":
        sv, sw = am["scale"]["v"], am["scale"]["w"]
        fv = poly_eval(am["coefficients"]["v"], ct["v"] / sv)
        cross = (am.get("cross") or {}).get("w", {}).get("v")     # turn rate += cross v / sv, when kept
        fw = poly_eval(am["coefficients"]["w"], ct["w"] / sw) + (cross or 0.0) * ct["v"] / sv
        out["turn_per_speed"] = None if cross is None else [round(cross / sv, 4), round(lin_of(world)["w_from_v"], 4)]
        out["coef_v"] = [round(c, 4) for c in am["coefficients"]["v"]]
        out["coef_w"] = [round(c, 4) for c in am["coefficients"]["w"]]
        out["scale"] = [sv, sw]
        out["lag_fitted"] = am.get("lag")
        rv = np.ptp(ct["v_true"]); rw = np.ptp(ct["w_true"])
        out["speed_err_pct"] = float(100 * np.sqrt(np.mean((fv - ct["v_true"]) ** 2)) / rv)
        out["turn_err_pct"] = float(100 * np.sqrt(np.mean((fw - ct["w_true"]) ** 2)) / rw)
        # the best the documented model class could do: LS fit of v_true by deg-2 poly in v,
        # of w_true by deg-1 poly in w (and v, when the model took the cross term)
        Av = np.column_stack([(ct["v"] / sv) ** i for i in range(len(am["coefficients"]["v"]))])
        Aw = np.column_stack([(ct["w"] / sw) ** i for i in range(len(am["coefficients"]["w"]))]
                             + ([ct["v"] / sv] if cross is not None else []))
        bv = np.linalg.lstsq(Av, ct["v_true"], rcond=None)[0]
        bw = np.linalg.lstsq(Aw, ct["w_true"], rcond=None)[0]
        out["speed_floor_pct"] = float(100 * np.sqrt(np.mean((Av @ bv - ct["v_true"]) ** 2)) / rv)
        out["turn_floor_pct"] = float(100 * np.sqrt(np.mean((Aw @ bw - ct["w_true"]) ** 2)) / rw)
        # slopes at the origin, fitted vs true small-signal gains
        lin = world["linear_map_no_saturation"]
        out["slope_v_fit_vs_true"] = [round(am["coefficients"]["v"][1] / sv, 4), round(lin["v_from_v"], 4)]
        out["slope_w_fit_vs_true"] = [round(am["coefficients"]["w"][1] / sw, 4), round(lin["w_from_w"], 4)]
    sm = m["sensor_model"]
    S = world["sensor"]
    out["reading_sigma"] = [sm.get("reading_sigma"), S.get("reading_sigma")]
    out["bearing_sigma"] = [sm.get("bearing_sigma"), S.get("bearing_sigma")]
    out["motion_noise"] = m.get("motion_noise")
    if sm.get("reading_poly") is not None and S["kind"] in ("range", "rssi"):
        ot = load_csv(os.path.join(log, "obs_truth.csv"))
        d = ot["distance"]
        basis = sm.get("reading_basis", "distance")
        u = d if basis == "distance" else 1.0 / d
        fit = poly_eval(sm["reading_poly"], u)
        if S["kind"] == "range":
            true = S["scale"] * d + S["bias"]
        else:
            true = -10 * S["n"] * np.log10(d) + S["A"]
        err = fit - true
        out["sensor_basis"] = basis
        out["reading_poly"] = [round(c, 5) for c in sm["reading_poly"]]
        out["sensor_curve_rms"] = float(np.sqrt(np.mean(err ** 2)))
        out["sensor_curve_rms_over_sigma"] = float(out["sensor_curve_rms"] / S["reading_sigma"])
        out["sensor_curve_maxerr"] = float(np.max(np.abs(err)))
    fitinfo = m.get("fit", {})
    out["fit_converged"] = fitinfo.get("converged")
    out["fit_iterations"] = fitinfo.get("iterations")
    out["outliers_set_aside"] = fitinfo.get("outliers_set_aside")
    out["sensor_degree"] = fitinfo.get("sensor_degree")
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--out", default="wheel_runs")
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--gen-args", default="", help="extra wheel_world.py arguments, e.g. '--base-tau 0.002'")
    ap.add_argument("--tag", default="", help="suffix of the case directory")
    ap.add_argument("--calibrate-args", default="", help="extra calibrate arguments, e.g. '--step-heading middle'")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    res_path = os.path.join(a.out, "results.jsonl")
    for case in a.cases:
        sensor, effect, seed = case.split(":")
        name = f"{sensor}_{effect}_s{seed}{a.tag}"
        base = os.path.join(a.out, name)
        if os.path.exists(base):
            shutil.rmtree(base)
        log, runp, diag = (os.path.join(base, d) for d in ("log", "run", "diag"))
        rec = {"case": name, "sensor": sensor, "effect": effect, "seed": int(seed), "gen_args": a.gen_args}
        t0 = time.time()
        subprocess.run([sys.executable, GENERATOR, log, "--minutes",
                        str(a.minutes), "--seed", seed, "--effect", effect, "--sensor", sensor] + a.gen_args.split(),
                       check=True, env=env)
        rec["gen_s"] = round(time.time() - t0, 1)
        world = json.load(open(os.path.join(log, "world_truth.json")))
        rec["world"] = {"track": world["robot"]["track"], "gains": [world["robot"]["gain_l"], world["robot"]["gain_r"]],
                        "vmax": world["robot"]["vmax"], "deadband": world["robot"]["deadband"],
                        "effect": world["effect"], "n_obs": world["n_observations"]}
        cmd = [CASM, "calibrate", log, "--out", runp, "--quiet"] + a.calibrate_args.split()
        rec["calibrate_cmd"] = " ".join(cmd)
        rc, err, sec = run(cmd, env)
        rec["calibrate_rc"], rec["calibrate_s"] = rc, round(sec, 1)
        rec["calibrate_stderr"] = clean_stderr(err)
        if rc == 0:
            try:
                rec.update(score(log, runp, world))
            except Exception as ex:  # noqa
                rec["score_error"] = repr(ex)
            cmd = [CASM, "diagnose", log, "--model", os.path.join(runp, "model.json"), "--out", diag,
                   "--quiet", "--workers", str(a.workers)]
            rec["diagnose_cmd"] = " ".join(cmd)
            rc, err, sec = run(cmd, env)
            rec["diagnose_rc"], rec["diagnose_s"] = rc, round(sec, 1)
            rec["diagnose_stderr"] = clean_stderr(err)
            if rc == 0:
                d = json.load(open(os.path.join(diag, "diagnosis.json")))
                rec["verdict"] = d.get("verdict")
                rec["candidates"] = [(c.get("effect"), c.get("channel"),
                                      None if c.get("delta_bic") is None else round(c["delta_bic"], 1),
                                      None if c.get("heldout_nll_drop") is None else round(c["heldout_nll_drop"], 1))
                                     for c in d.get("candidates", [])[:4]]
                rec["summary"] = d.get("summary", [])[:3]
                rec["top_covariates"] = {ch: [(c["name"], round(c["strength"], 3), c.get("kind"))
                                              for c in v.get("covariates", [])[:2]]
                                         for ch, v in d.get("channels", {}).items()}
                rec["channel_rms"] = {ch: v.get("rms") for ch, v in d.get("channels", {}).items()}
                rec["lookalikes"] = [l.get("effects") for l in d.get("lookalikes", [])]
        with open(res_path, "a") as f:
            f.write(json.dumps(rec) + "\n")
        f = lambda k, p=3: ("-" if rec.get(k) is None else (f"{rec[k]:.{p}f}" if isinstance(rec[k], float) else str(rec[k])))
        sig = rec.get("reading_sigma", [None, None]); bsig = rec.get("bearing_sigma", [None, None])
        fs = lambda z: "-" if z is None else f"{z:.3g}"
        print(f"{name:28s} cal_rc={rec['calibrate_rc']} {f('calibrate_s',0)}s diag_rc={rec.get('diagnose_rc','-')} "
              f"{f('diagnose_s',0)}s pos={f('pos_rms')}m speed={f('speed_err_pct',1)}%(floor {f('speed_floor_pct',1)}) "
              f"turn={f('turn_err_pct',1)}%(floor {f('turn_floor_pct',1)}) rsig={fs(sig[0])}/{fs(sig[1])} "
              f"bsig={fs(bsig[0])}/{fs(bsig[1])} curve={f('sensor_curve_rms')} verdict={rec.get('verdict','-')}"
              + (f" turn_per_speed={rec['turn_per_speed']}" if rec.get("turn_per_speed") else ""),
              flush=True)
        for k in ("calibrate_stderr", "diagnose_stderr"):
            if rec.get(k) and (rec.get(k.split('_')[0] + "_rc") not in (0,)):
                print("   ", k, rec[k][:2], "...", rec[k][-2:], flush=True)


if __name__ == "__main__":
    main()
