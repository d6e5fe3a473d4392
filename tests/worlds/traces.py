"""Does a diagnosis report's first panel show a test world's hidden effect? Checked against the world's truth.

Each catalog effect's view (``Effect.signature``, drawn first by the report) is checked for what a reader should see
in it: the residuals against a covariate the effect explains depart from zero (the test's p), the motion residuals'
correlation with the commands' changes leaves its white-noise band, the forward residuals are lower on the carpet
than off it, the motion achieved falls over time, the landmarks' sightings disagree (one landmark's move is spread
over the map's shape, so the one furthest off need not be the one moved: recorded, not required), the sightings'
tails are heavier than a normal's.
"""
from __future__ import annotations

import numpy as np

from casm_graph.analysis.correlation import strongest
from casm_graph.analysis.trace_measures import landmark_means, moving, normal_tail, speed_trend, tail_share
from casm_graph.models.effects import REGISTRY, get as get_effect
from casm_graph.report.signature import lead

P_SHOWN = 1e-3            # a covariate panel shows a dependence at this p or below
BAND_SHOWN = 1.0          # a correlation panel shows structure beyond this multiple of its band
FIELD_Z = 3.0             # the carpet's forward residuals below the rest by this many standard errors
FADE_T = 3.0              # the motion achieved falls over time by this many standard errors
TAIL_SHOWN = 10 * normal_tail(4.0)   # ten times the normal's share beyond 4 sigmas


def field_z(diag, patch: dict) -> float:
    """z of the mean forward residual on the carpet ``patch`` against off it (negative: slower on it)."""
    d = diag.residuals["forward"]
    x, y, r = d.covariates["x"], d.covariates["y"], d.residual
    on = (x >= patch["xmin"]) & (x <= patch["xmax"]) & (y >= patch["ymin"]) & (y <= patch["ymax"])
    if on.sum() < 5 or (~on).sum() < 5:
        return float("nan")
    diff = r[on].mean() - r[~on].mean()
    return float(diff / np.sqrt(r[on].var() / on.sum() + r[~on].var() / (~on).sum()))


def most_off(diag) -> int | None:
    """The landmark whose sightings' mean residual stands furthest off zero (in standard errors), either channel."""
    best, worst = None, 0.0
    for ch in ("reading", "bearing"):
        if ch in diag.residuals:
            ids, m, se = landmark_means(diag, ch)
            z = np.abs(m) / np.maximum(se, 1e-12)
            if len(z) and z.max() > worst:
                best, worst = int(ids[np.argmax(z)]), float(z.max())
    return best


def check(diag, effect: str | None, geom: dict) -> dict:
    """The report's first view for ``diag``, where among its opening views (the verdict's, then its look-alikes')
    the world's hidden ``effect`` has its own (``position``, None if absent) and whether that view shows it (its
    truth's geometry ``geom``: a carpet's ``patch``, a moved ``landmark``); ``shown`` None when the world hid no
    catalog effect."""
    views = lead(diag)
    out = {"lead": views[0].kind if views else None, "lead_effects": list(views[0].effects) if views else None}
    cls = get_effect(effect) if effect in REGISTRY else None
    if cls is None:
        return {**out, "expected": None, "position": None, "shown": None}
    out["expected"] = cls.signature
    position = next((k for k, v in enumerate(views) if effect in (e.partition(":")[0] for e in v.effects)), None)
    if position is None:
        return {**out, "position": None, "shown": False}
    view = views[position]
    out["position"] = position
    if view.kind == "covariates":
        ch, test = view.pairs[0] if view.pairs else ("", {"name": "", "p": 1.0})
        out.update(measure=f"{ch} vs {test['name']}", p=float(test["p"]),
                   shown=(ch, test["name"]) in set(cls.explains) and test["p"] <= P_SHOWN)
    elif view.kind == "correlation":
        ch, ratio = strongest(diag.correlation)
        out.update(measure=f"{ch} correlation / band", ratio=ratio, shown=ratio > BAND_SHOWN)
    elif view.kind == "field":
        z = field_z(diag, geom["patch"])
        out.update(measure="forward residual on the carpet, z", z=z, shown=bool(z <= -FIELD_Z))
    elif view.kind == "landmarks":
        p = min((c["p"] for ch in ("reading", "bearing") if ch in diag.channels
                 for c in diag.channels[ch]["covariates"] if c["name"] == "landmark"), default=1.0)
        out.update(measure="sightings vs landmark", p=float(p), furthest_off=most_off(diag),
                   moved=geom.get("landmark"), shown=p <= P_SHOWN)
    elif view.kind == "speed":
        o = diag.options
        trends = {ch: speed_trend(diag.residuals[ch], o.trend_block, o.trend_memory)[1] for ch in moving(diag)}
        ch = min(trends, key=trends.get)
        out.update(measure=f"{ch} achieved share per minute, t", t=trends[ch], shown=trends[ch] <= -FADE_T)
    else:
        share = max(tail_share(diag.residuals[ch].residual) for ch in ("reading", "bearing") if ch in diag.residuals)
        out.update(measure="share beyond 4 sigmas", share=share, set_aside=diag.set_aside,
                   shown=share >= TAIL_SHOWN or diag.set_aside > 0)
    return out
