"""Drift over time: which robot's calibrated model changed between sessions by more than its uncertainty allows.

Input: each session's model.json (robot, time, the model). For every robot, every model figure is
followed over its sessions with its posterior standard deviation:

* ``velocities`` (action tables): each action's vx, vy, w with the table's ``std``;
* ``command_map`` (continuous commands): the coefficients of f_v and f_w with their ``std``, in the
  command's own units (model.json's divided by ``scale``^i: each log has its own scale);
* ``sensor``: the reading polynomial's coefficients with ``reading_poly_std``;
* ``effects``: fitted effect parameters with ``fit.effects_std`` when the run has them;
* ``noise``: reading and bearing sigma and the motion noise, shown but never flagged (no std).

A figure is **flagged** between two sessions a, b (consecutive ones, and the first against each
later one) when |x_b - x_a| > Z sqrt(s_a^2 + s_b^2) and the change is at least MIN_REL of |x_a|
(so that a tiny std does not flag noise). Across a fleet thousands of figures are compared and a
calibration now and then gets an action wrong, so figure flags come by chance; a robot is said to
have **drifted** per family, with the fleet's false-alarm rate held at ALPHA:

* ``velocities`` / ``command_map``: a common scale k with x_b = k x_a (maximum likelihood with both
  sessions noisy: k minimises sum (x_b - k x_a)^2 / (s_b^2 + k^2 s_a^2)), leaving out figures more
  than OUTLIER sigma off the common scale (at most MAX_OUTLIERS of them, so that a few actions one
  calibration got wrong do not move k). The family drifted when |k - 1| > Z_f sd(k) and
  |k - 1| > MIN_REL, where Z_f = max(Z, the two-sided Bonferroni quantile of ALPHA over the fleet's
  comparisons of that family) (3 sigma for a few robots, 3.6 for 20 robots x 5 days); or when more of
  its actions (coefficients of a command map) flagged than chance allows: binomial tail below
  ALPHA / comparisons, at the larger of the nominal rate and the fleet's median flag rate;
* ``sensor``: the same scale test on the reading curve at four distances both sessions saw, with the
  polynomial's full covariance when model.json has it (else the coefficients with their std); its
  coefficients are strongly correlated, so their flag count is not used.

Each drifted family gives one readable line, e.g. ``robot03: velocities scaled by 0.92 since
2026-03-01 (on 2026-03-05, 9.1 sigma; 17 of 36 actions beyond 3 sigma)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import norm

from casm_graph.models.model import ACTION_MODELS
from casm_graph.models.velocity_table import AXES, json_number
from factors.reading import BASES, features

Z = 3.0                 # sigmas a change must exceed
MIN_REL = 0.03          # and this share of the earlier value
ALPHA = 0.05            # chance of any false family flag in the whole fleet
OUTLIER = 4.0           # sigmas off the common scale: a figure left out of the scale (a calibration's bad action)
MAX_OUTLIERS = 0.2      # at most this share of the figures left out
FLAGGED_FAMILIES = ("velocities", "command_map", "sensor", "effects")
SCALE_FAMILIES = ("velocities", "command_map", "sensor")


@dataclass
class Session:
    """One calibrated log of one robot: its model.json content."""

    robot: str
    time: str
    path: str
    model: dict


@dataclass
class Drift:
    """The analysis: per robot its series, the flagged figures and the per-family comparisons."""

    series: dict = field(default_factory=dict)       # robot -> {"times", "paths", "parameters": {name: {...}}}
    flags: list = field(default_factory=list)        # flagged figures (every comparison)
    families: list = field(default_factory=list)     # every family comparison, flagged or not
    z: float = Z
    min_rel: float = MIN_REL
    family_z: dict = field(default_factory=dict)        # family -> the threshold its comparisons met
    unit_flag_rate: dict = field(default_factory=dict)  # family -> median share of flagged actions per robot

    @property
    def drifted(self) -> dict[str, list[str]]:
        """robot -> families that drifted."""
        out: dict[str, list[str]] = {}
        for f in self.families:
            if f["flagged"] and f["family"] not in out.get(f["robot"], []):
                out.setdefault(f["robot"], []).append(f["family"])
        return out

    @property
    def summary(self) -> list[str]:
        """One line per drifted robot and family (its strongest comparison), then the strongest figure flags."""
        lines = []
        best: dict[tuple, dict] = {}
        for f in self.families:
            if f["flagged"]:
                k = (f["robot"], f["family"])
                if k not in best or abs(f["sigma"]) > abs(best[k]["sigma"]):
                    best[k] = f
        lines += [best[k]["text"] for k in sorted(best)]
        return lines

    @property
    def strongest_flags(self) -> list[dict]:
        """Per robot and figure its strongest flag, robots in order, strongest first within a robot."""
        best: dict[tuple, dict] = {}
        for f in self.flags:
            k = (f["robot"], f["parameter"])
            if k not in best or abs(f["sigma"]) > abs(best[k]["sigma"]):
                best[k] = f
        return sorted(best.values(), key=lambda f: (f["robot"], -abs(f["sigma"])))

    def to_json(self) -> dict:
        return {"z": self.z, "min_relative_change": self.min_rel, "family_z": self.family_z,
                "unit_flag_rate": self.unit_flag_rate, "drifted": self.drifted, "summary": self.summary,
                "families": self.families, "flags": self.flags, "series": self.series}


# --------------------------------------------------------------------------- the figures of one model

def parameters(model: dict) -> dict[str, dict]:
    """name -> {"family", "value", "std"} for every figure of one model.json (std NaN where unknown)."""
    out: dict[str, dict] = {}

    def put(name, family, value, std=math.nan):
        out[name] = {"family": family, "value": json_number(value), "std": json_number(std)}

    am = model.get("action_model", {}) or {}
    part = ACTION_MODELS.get(am.get("kind"))
    for name, family, value, std in part.figures(am) if part is not None else ():
        put(name, family, value, std)
    sm = model.get("sensor_model", {}) or {}
    poly = sm.get("reading_poly") or []
    psd = sm.get("reading_poly_std") or [None] * len(poly)
    basis = sm.get("reading_basis", "distance")     # coefficients in different variables are not the same figure
    for i, c in enumerate(poly):
        put(f"reading c{i}" + ("" if basis == "distance" else f" ({basis})"), "sensor", c, psd[i] if i < len(psd) else None)
    put("reading_sigma", "noise", sm.get("reading_sigma"))
    put("bearing_sigma", "noise", sm.get("bearing_sigma"))
    for ax, v in zip(("x", "y", "theta"), model.get("motion_noise") or []):
        put(f"motion_noise {ax}", "noise", v)
    estd = (model.get("fit", {}) or {}).get("effects_std", {}) or {}
    for name, params in (model.get("effects", {}) or {}).items():
        for p, v in (params or {}).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                put(f"{name}.{p}", "effects", v, (estd.get(name) or {}).get(p))
    return out


def _curve(model: dict, d: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The reading curve at distances ``d`` and its covariance (from reading_poly_cov, else the coefficients' std)."""
    sm = model.get("sensor_model", {}) or {}
    poly = np.array([json_number(c) for c in sm.get("reading_poly") or []])
    if len(poly) == 0 or not np.isfinite(poly).all():
        return None
    basis = sm.get("reading_basis", "distance")
    if basis not in BASES:
        return None
    V = features(d, len(poly), basis)[0]
    cov = sm.get("reading_poly_cov")
    if cov is not None:
        C = np.array([[json_number(x) for x in row] for row in cov])
    else:
        sd = np.array([json_number(s) for s in (sm.get("reading_poly_std") or [None] * len(poly))])
        C = np.diag(sd ** 2)
    if C.shape != (len(poly), len(poly)) or not np.isfinite(C).all():
        return None
    return V @ poly, V @ C @ V.T


# --------------------------------------------------------------------------- tests between two sessions

def _binom_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p)."""
    if k <= 0:
        return 1.0
    return float(sum(math.comb(n, i) * p ** i * (1 - p) ** (n - i) for i in range(k, n + 1)))


def scale_test(xa: np.ndarray, xb: np.ndarray, Ca: np.ndarray, Cb: np.ndarray) -> tuple[float, float]:
    """(k, sd(k)) of x_b = k x_a by maximum likelihood with both sides noisy: k minimises
    f(k) = (x_b - k x_a)' (Cb + k^2 Ca)^-1 (x_b - k x_a) (no regression dilution), sd(k) = sqrt(2 / f''(k))."""

    xa, xb, Ca, Cb = (np.asarray(v, float) for v in (xa, xb, Ca, Cb))
    if len(xa) == 0 or not np.any(xa):
        return math.nan, math.nan
    diag = np.count_nonzero(Ca - np.diag(np.diag(Ca))) == 0 and np.count_nonzero(Cb - np.diag(np.diag(Cb))) == 0
    va, vb = np.diag(Ca), np.diag(Cb)

    def f(k):
        d = xb - k * xa
        if diag:
            return float(np.sum(d * d / (vb + k * k * va)))
        C = Cb + k * k * Ca
        try:
            return float(d @ np.linalg.solve(C, d))
        except np.linalg.LinAlgError:
            return float(d @ np.linalg.lstsq(C, d, rcond=None)[0])

    res = minimize_scalar(f, bounds=(0.05, 20.0), method="bounded", options={"xatol": 1e-7})
    k = float(res.x)
    h = 1e-4 * max(1.0, abs(k))
    curv = (f(k + h) - 2 * f(k) + f(k - h)) / (h * h)
    return (k, math.sqrt(2.0 / curv)) if curv > 0 else (k, math.nan)


def robust_scale(xa, xb, sa, sb, cut: float = OUTLIER, share: float = MAX_OUTLIERS) -> tuple[float, float, np.ndarray]:
    """(k, sd(k), kept) of x_b = k x_a from independent figures, leaving out those more than ``cut`` sigma off
    the common scale (at most ``share`` of them): a few actions a calibration got wrong do not move k."""
    xa, xb, sa, sb = (np.asarray(v, float) for v in (xa, xb, sa, sb))
    keep = np.ones(len(xa), bool)
    k, sk = math.nan, math.nan
    for _ in range(10):
        k, sk = scale_test(xa[keep], xb[keep], np.diag(sa[keep] ** 2), np.diag(sb[keep] ** 2))
        if not np.isfinite(k):
            return k, sk, keep
        r = np.abs(xb - k * xa) / np.sqrt(sb ** 2 + k * k * sa ** 2)
        new = r <= cut
        if (~new).sum() > share * len(xa):             # too many to be a few bad actions: keep the closest
            new = r <= np.quantile(r, 1 - share)
        if np.array_equal(new, keep):
            break
        keep = new
    return k, sk, keep


def _p_chance(z: float) -> float:
    return math.erfc(z / math.sqrt(2))


def compare(robot: str, a: Session, b: Session, pa: dict, pb: dict, kind: str, z: float = Z,
            min_rel: float = MIN_REL) -> tuple[list[dict], list[dict]]:
    """Figure flags and family comparisons between sessions ``a`` (earlier) and ``b``. Command maps of two forms
    (one with the turn map's term in v, ``w from v``, one without) are not compared: the other coefficients
    absorb the term differently."""
    flags, fams = [], []
    tested: dict[str, list] = {}
    unlike = {"command_map"} if ("w from v" in pa) != ("w from v" in pb) else set()
    for name in pa.keys() & pb.keys():
        fa, fb = pa[name], pb[name]
        if fa["family"] not in FLAGGED_FAMILIES or fa["family"] in unlike:
            continue
        xa, xb, sa, sb = fa["value"], fb["value"], fa["std"], fb["std"]
        if not all(math.isfinite(v) for v in (xa, xb, sa, sb)) or sa <= 0 or sb <= 0:
            continue
        s = math.hypot(sa, sb)
        sigma = (xb - xa) / s
        rel = (xb - xa) / xa if xa != 0 else math.inf          # -8 %: 8 % smaller in magnitude
        hit = abs(sigma) > z and abs(xb - xa) > min_rel * abs(xa)
        tested.setdefault(fa["family"], []).append((name, xa, xb, sa, sb, hit))
        if hit:
            rel_txt = f"{100 * rel:+.1f} %" if math.isfinite(rel) else f"{xb - xa:+.4g} (from 0)"
            flags.append({"robot": robot, "family": fa["family"], "parameter": name, "since": a.time, "time": b.time,
                          "comparison": kind, "before": xa, "after": xb, "std_before": sa, "std_after": sb,
                          "relative_change": rel if math.isfinite(rel) else None, "sigma": sigma,
                          "text": f"{robot}: {name} {rel_txt} since {a.time} (on {b.time}, {abs(sigma):.1f} sigma)"})
    for family in SCALE_FAMILIES:
        rows = tested.get(family, [])
        if family == "sensor":
            res = _sensor_scale(a.model, b.model)
        elif rows:
            k, sk, kept = robust_scale(*(np.array([r[i] for r in rows]) for i in (1, 2, 3, 4)))
            res = (k, sk)
            left_out = int((~kept).sum())
        else:
            res = None
        if res is None or not np.isfinite(res[0]):
            continue
        if family == "sensor":
            left_out = 0
        k, sk = res
        n_hit = sum(r[5] for r in rows)
        units, units_hit, what, p_unit = len(rows), n_hit, "coefficients", _p_chance(z)
        if family == "velocities":          # an action is one unit: a bad fit of one action moves its three figures
            acts = {}
            for r in rows:
                act = r[0].rsplit(" ", 1)[0]
                acts[act] = acts.get(act, False) or r[5]
            units, units_hit, what = len(acts), sum(acts.values()), "actions"
            p_unit = 1 - (1 - p_unit) ** len(AXES)
        fams.append({"robot": robot, "family": family, "since": a.time, "time": b.time, "comparison": kind,
                     "scale": k, "scale_std": sk, "sigma": (k - 1) / sk, "beyond": n_hit, "tested": len(rows),
                     "left_out_of_scale": left_out, "units_beyond": units_hit, "units": units, "unit": what,
                     "p_unit_nominal": p_unit})
    return flags, fams


def _sensor_scale(ma: dict, mb: dict) -> tuple[float, float] | None:
    """Scale of session b's reading curve against session a's at four distances both saw."""
    ra = (ma.get("sensor_model", {}) or {}).get("distance_range") or [0, 0]
    rb = (mb.get("sensor_model", {}) or {}).get("distance_range") or [0, 0]
    lo, hi = max(json_number(ra[0]), json_number(rb[0])), min(json_number(ra[1]), json_number(rb[1]))
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        return None
    d = np.linspace(lo, hi, 4)
    ca, cb = _curve(ma, d), _curve(mb, d)
    if ca is None or cb is None:
        return None
    return scale_test(ca[0], cb[0], ca[1], cb[1])


# --------------------------------------------------------------------------- the fleet

def analyse(sessions: list[Session], z: float = Z, min_rel: float = MIN_REL, alpha: float = ALPHA) -> Drift:
    """Series, flags and family comparisons of every robot with its sessions in time order."""
    out = Drift(z=z, min_rel=min_rel)
    robots: dict[str, list[Session]] = {}
    for s in sessions:
        robots.setdefault(str(s.robot), []).append(s)
    for robot in sorted(robots):
        ss = sorted(robots[robot], key=lambda s: (str(s.time), s.path))
        ps = [parameters(s.model) for s in ss]
        names = sorted(set().union(*ps), key=_order)
        out.series[robot] = {
            "times": [s.time for s in ss], "paths": [s.path for s in ss],
            "parameters": {n: {"family": next(p[n]["family"] for p in ps if n in p),
                               "values": [p[n]["value"] if n in p else None for p in ps],
                               "std": [p[n]["std"] if n in p else None for p in ps]} for n in names}}
        pairs = [(i - 1, i, "consecutive") for i in range(1, len(ss))] + [(0, i, "from_first") for i in range(2, len(ss))]
        for i, j, kind in pairs:
            f, fam = compare(robot, ss[i], ss[j], ps[i], ps[j], kind, z, min_rel)
            out.flags += f
            out.families += fam
    decide(out, alpha)
    return out


def family_z(z: float, tests: int, alpha: float = ALPHA) -> float:
    """The family threshold: ``z``, or more when the fleet holds so many comparisons that ``z`` alone would
    flag one by chance (Bonferroni: at most ``alpha`` chance of any false family flag in the fleet)."""
    return max(z, float(norm.isf(alpha / (2 * max(tests, 1)))))


def decide(out: Drift, alpha: float = ALPHA) -> None:
    """Flag family comparisons with fleet-wide thresholds (see the module docstring) and word them."""
    z, min_rel = out.z, out.min_rel
    for family in SCALE_FAMILIES:
        fams = [f for f in out.families if f["family"] == family]
        if not fams:
            continue
        zf = family_z(z, len(fams), alpha)
        out.family_z[family] = zf
        per_robot: dict[str, list[int]] = {}
        for f in fams:
            c = per_robot.setdefault(f["robot"], [0, 0])
            c[0] += f["units_beyond"]
            c[1] += f["units"]
        rates = [h / n for h, n in per_robot.values() if n]
        p_emp = float(np.median(rates)) if rates else 0.0
        out.unit_flag_rate[family] = p_emp
        for f in fams:
            k, sigma = f["scale"], f["sigma"]
            p_unit = max(f["p_unit_nominal"], p_emp)
            tail = _binom_tail(f["units_beyond"], f["units"], p_unit)
            by_scale = bool(abs(sigma) > zf and abs(k - 1) > min_rel)
            by_count = bool(family != "sensor" and f["units_beyond"] >= 2 and tail < alpha / len(fams))
            label = {"velocities": "velocities", "command_map": "command map", "sensor": "sensor curve"}[family]
            detail = f"{f['units_beyond']} of {f['units']} {f['unit']} beyond {z:g} sigma"
            if by_scale:
                text = (f"{f['robot']}: {label} scaled by {k:.3f} since {f['since']} (on {f['time']}, "
                        f"{abs(sigma):.1f} sigma; {detail})")
            else:
                text = (f"{f['robot']}: {label}: {detail} since {f['since']} (on {f['time']}; chance would give "
                        f"so many with p {tail:.1g})")
            f.update(chance_p=tail, by_scale=by_scale, by_count=by_count, flagged=by_scale or by_count, text=text)


def _order(name: str):
    """Actions by number, then the rest by name."""
    parts = name.split()
    if parts[0] == "action" and len(parts) == 3 and parts[1].lstrip("-").isdigit():
        return (0, int(parts[1]), AXES.index(parts[2]) if parts[2] in AXES else 9, "")
    return (1, 0, 0, name)
