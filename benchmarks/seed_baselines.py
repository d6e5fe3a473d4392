"""Full-size checks of the two seed baselines (issue 6), printed as the tables BENCHMARKS.md records.

SCASM: 10 trials of the 1-D protocol, 2.5 min each: the paper's algorithm and the 1-D ISAM2 graph,
scored as the paper scores (best scale / scale + offset fit, scale-consistency ratio).
MCL: the region-dependent floor, default static / optimal static / global / regional dynamic MCL,
localisation error, the regional map, and the graph's two joint per-region estimates: ``mcl.graph_em``
(known start and sensor) and the catalog effect regional_motion_noise on the continuous-command
calibration (sensor curve, command map and trajectory learned with it). Per-region errors are taken
over the regions the true path spent at least MIN_SEGMENTS steps in.

    python benchmarks/seed_baselines.py --scasm-trials 10 --mcl-seeds 0 1 2 3 4
    python benchmarks/seed_baselines.py --scasm-trials 0 --mcl-seeds --sweep-seeds 20   # MCL vs sensing density
"""
import argparse
import time

import numpy as np

from casm_graph.baselines import mcl, scasm
from casm_graph.fit import continuous
from casm_graph.models.effects.regional_motion_noise import Regions, from_entry
from casm_graph.sim.floor import FloorConfig, region_of
from casm_graph.sim.floor import simulate as simfloor
from casm_graph.sim.walk_1d import Sim1DConfig
from casm_graph.sim.walk_1d import simulate as sim1d


def scasm_trials(n: int, minutes: float = 2.5) -> dict:
    rows = {"scasm": [], "graph": [], "start": [], "best": []}
    secs = {"scasm": [], "graph": []}
    for seed in range(n):
        log, truth = sim1d(Sim1DConfig(minutes=minutes, seed=seed))
        walk = scasm.walk_of(log)
        on = scasm.online(walk)
        gr = scasm.graph_online(walk)
        for name, res in (("scasm", on), ("graph", gr)):
            s = scasm.score(res.action, res.sensor, truth)
            rows[name].append((s.action_rms, s.sensor_rms, s.consistency))
            secs[name].append(res.seconds)
        rows["start"].append(scasm.score(lambda c: c, on.sensor, truth).action_rms)
        rows["best"].append((truth["action_model"]["best_quartic_rms_mm_s"], truth["sensor_model"]["best_cubic_rms_mm"]))
        print(f"trial {seed}: scasm {rows['scasm'][-1]}, graph {rows['graph'][-1]}", flush=True)
    return {k: np.array(v) for k, v in rows.items()} | {"seconds": {k: np.mean(v) for k, v in secs.items()}}


def mcl_seed(seed: int, minutes: float = 10.0, detect_prob: float | None = None) -> dict:
    cfg = FloorConfig(seed=seed, minutes=minutes, **({} if detect_prob is None else {"detect_prob": detect_prob}))
    log, truth = simfloor(cfg)
    K_true = np.array(truth["motion_model"]["region_k"])
    drive = mcl.drive_of(log)
    out = {}
    runs = mcl.run_modes(drive, cfg.size, cfg.grid, seed=seed)
    for name, r in runs.items():
        out[name] = mcl.errors(r.poses, log.truth)
    reg = runs["regional dynamic"]
    k_pairs = mcl.regional_fit(reg.pairs, len(K_true))
    t0 = time.perf_counter()
    g = mcl.graph_em(drive, cfg.size, cfg.grid, reg.poses)
    out["graph seconds"] = time.perf_counter() - t0
    out["graph iterations"] = g.iterations
    t0 = time.perf_counter()
    fit = continuous.fit_with_effects(log, effects=["regional_motion_noise"], marginals=False,
                                      regions=Regions((0.0, 0.0, *cfg.size), cfg.grid))
    out["effect seconds"] = time.perf_counter() - t0
    K_eff = from_entry(fit.model.effects["regional_motion_noise"])[1]
    seen = mcl.regions_seen(log.truth, cfg.size, cfg.grid)
    idx = np.flatnonzero(seen)
    out["k"] = {name: (mcl.log_error(K[seen], K_true[seen]), mcl.rough_among(K, seen),
                       mcl.variance_error(K[seen], K_true[seen]))
                for name, K in (("mcl map (final windows)", reg.k_final), ("mcl all pairs per region", k_pairs),
                                ("graph EM", g.k), ("graph effect regional_motion_noise", K_eff))}
    out["true rough"] = sorted(set(cfg.rough) & set(idx.tolist()))
    out["regions seen"] = int(seen.sum())
    # what MCL's pairs measure: the motion error plus the change in MCL's own localisation error
    tp = log.truth[:, 1:]
    region = region_of(tp[:-1, :2], cfg.size, cfg.grid)
    true_r = np.cos(tp[:-1, 2]) * np.diff(tp[:, 0]) + np.sin(tp[:-1, 2]) * np.diff(tp[:, 1])
    true_err, mcl_err = true_r - reg.pairs[:, 0], reg.pairs[:, 2] - reg.pairs[:, 0]
    out["mcl excess by region"] = [float(np.mean(mcl_err[region == g] ** 2) / np.mean(true_err[region == g] ** 2))
                                   for g in range(len(K_true))]
    out["landmarks by region"] = np.bincount(region_of(np.unique(log.landmark_xy, axis=0), cfg.size, cfg.grid),
                                             minlength=len(K_true)).tolist()
    paper_worst = mcl.default_worst(out, "range_error_pct") and mcl.default_worst(out, "angle_error_pct")
    print(f"seed {seed}: default worst in range and angle error: {paper_worst}; "
          + "; ".join(f"{k}: log err {v[0]:.2f}, var err {v[2]:.2f}, rough {v[1]}" for k, v in out["k"].items()), flush=True)
    print(f"  mean square of MCL's translation errors / of the true ones, by region: "
          f"{np.round(out['mcl excess by region'], 1).tolist()}, "
          f"landmarks by region: {out['landmarks by region']}", flush=True)
    out["graph smoothed"] = mcl.errors(g.poses, log.truth)
    return out


def sensing_sweep(n_seeds: int, detect_probs, minutes: float = 10.0) -> None:
    """MCL alone (it takes seconds) over many floors and sensing densities: how often the regional map
    finds the rough regions and default static is the worst of the four (Table 1's order), per quantity."""
    print("\n| chance a landmark in view is seen per step | MCL map right | default worst: range % | angle % "
          "| position RMS | range and angle % | map right and default worst in both | median RMS log(var/var_true) |")
    print("|---|---|---|---|---|---|---|---|")
    for p in detect_probs:
        rows = []
        for seed in range(n_seeds):
            t = mcl.floor_trial(FloorConfig(seed=seed, minutes=minutes, detect_prob=p))
            worst = list(t["default_worst"].values())
            rows.append((t["map_right"], *worst, worst[0] and worst[1], t["map_right"] and worst[0] and worst[1],
                         t["variance_error"]))
        a = np.array(rows)
        n = len(a)
        print(f"| {p} | " + " | ".join(f"{int(c.sum())}/{n}" for c in a[:, :6].T) + f" | {np.median(a[:, 6]):.2f} |",
              flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scasm-trials", type=int, default=10)
    ap.add_argument("--mcl-seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    ap.add_argument("--mcl-minutes", type=float, default=10.0)
    ap.add_argument("--detect-prob", type=float, default=None, help="floor: chance each landmark in view is seen per step")
    ap.add_argument("--sweep-seeds", type=int, default=0, help="MCL alone over this many floors per sensing density")
    ap.add_argument("--sweep-detect", type=float, nargs="*", default=[0.2, 0.5, 0.7, 1.0])
    a = ap.parse_args()
    if a.sweep_seeds:
        sensing_sweep(a.sweep_seeds, a.sweep_detect, a.mcl_minutes)
    if a.scasm_trials:
        r = scasm_trials(a.scasm_trials)
        print("\n| method | action RMS mm/s | sensor RMS mm | abs(abs(ratio) - 1) | seconds per trial |")
        print("|---|---|---|---|---|")
        print("| paper (Aibo, 10 trials) | 29.6 ± 12.4 | 70.4 ± 13.9 | 0.08 ± 0.06 | - |")
        for name in ("scasm", "graph"):
            m, s = r[name].mean(0), r[name].std(0)
            print(f"| {name} | {m[0]:.1f} ± {s[0]:.1f} | {m[1]:.1f} ± {s[1]:.1f} | {m[2]:.3f} ± {s[2]:.3f} | {r['seconds'][name]:.1f} |")
        print(f"| start A0(c) = c | {r['start'].mean():.1f} | | | |")
        print(f"| best quartic / cubic | {r['best'][:, 0].mean():.1f} | {r['best'][:, 1].mean():.1f} | | |")
        print(f"graph better than scasm: action on {np.sum(r['graph'][:, 0] <= r['scasm'][:, 0])}/{len(r['scasm'])} trials, "
              f"sensor on {np.sum(r['graph'][:, 1] <= r['scasm'][:, 1])}/{len(r['scasm'])}")
    if a.mcl_seeds:
        res = [mcl_seed(s, a.mcl_minutes, a.detect_prob) for s in a.mcl_seeds]
        modes = ["default", "optimal static", "global dynamic", "regional dynamic"]
        print("\n| MCL | position RMS m | heading RMS rad | range error % | angle error % |")
        print("|---|---|---|---|---|")
        for m in modes + ["graph smoothed"]:
            e = np.array([[o[m][k] for k in ("position_rms", "heading_rms", "range_error_pct", "angle_error_pct")] for o in res])
            print(f"| {m} | {e[:, 0].mean():.4f} | {e[:, 1].mean():.4f} | {e[:, 2].mean():.1f} | {e[:, 3].mean():.1f} |")
        worst = sum(all(o["default"]["position_rms"] > o[m]["position_rms"] for m in modes[1:]) for o in res)
        pw = sum(all(o["default"][c] > o[m][c] for m in modes[1:] for c in ("range_error_pct", "angle_error_pct"))
                 for o in res)
        print(f"default static worst in position on {worst}/{len(res)} seeds, in both range % and angle % on {pw}/{len(res)}")
        print("\n| per-region k estimate | RMS log(k/k_true), median over seeds | RMS log(var/var_true) | rough regions right |")
        print("|---|---|---|---|")
        for name in res[0]["k"]:
            err = np.median([o["k"][name][0] for o in res])
            verr = np.median([o["k"][name][2] for o in res])
            right = sum(o["k"][name][1] == o["true rough"] for o in res)
            print(f"| {name} | {err:.2f} | {verr:.2f} | {right}/{len(res)} |")
        wrong = [(o["mcl excess by region"][g], np.median([o["mcl excess by region"][h] for h in range(len(o["landmarks by region"]))
                                                           if h not in o["true rough"] and h != g]))
                 for o in res for g in o["k"]["mcl map (final windows)"][1] if g not in o["true rough"]]
        if wrong:
            print("smooth regions the MCL map calls rough: MCL's translation errors inflate the true ones' mean square there "
                  "by (vs the other smooth regions' median): " + ", ".join(f"{a:.1f}x vs {b:.1f}x" for a, b in wrong))
        for g in ("graph EM", "graph effect regional_motion_noise"):
            closer = sum(o["k"][g][0] <= min(o["k"]["mcl map (final windows)"][0], o["k"]["mcl all pairs per region"][0])
                         for o in res)
            vcloser = sum(o["k"][g][2] <= min(o["k"]["mcl map (final windows)"][2], o["k"]["mcl all pairs per region"][2])
                          for o in res)
            print(f"{g} closer to the true k's than both MCL estimates on {closer}/{len(res)} seeds, "
                  f"to the true motion variances on {vcloser}/{len(res)}")
        print(f"graph EM: {np.mean([o['graph seconds'] for o in res]):.1f} s, "
              f"{np.mean([o['graph iterations'] for o in res]):.0f} iterations on average; the effect's calibration "
              f"{np.mean([o['effect seconds'] for o in res]):.0f} s; regions visited "
              f"{[o['regions seen'] for o in res]}")


if __name__ == "__main__":
    main()
