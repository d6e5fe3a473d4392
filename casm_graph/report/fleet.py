"""OUT/report.html of a fleet: the fleet side by side, the drift findings, each robot's figures over time.

Figures are ``matplotlib.figure.Figure`` objects (never pyplot: the fleet may run inside a notebook or a
worker) embedded as base64 PNG. Per robot: the scale of its action model and of its sensor curve
against its first session (with 1-sigma error bars), the figures that flagged over time with their
posterior std, and the noise levels relative to the first session (shown, never flagged); flagged
points are red.
"""
from __future__ import annotations

import html
import math

import numpy as np
from matplotlib.figure import Figure

from casm_graph.report.pages import png

SHOWN = ("path", "robot", "time", "status", "steps", "minutes", "actions", "mean_abs_vx", "mean_abs_vy",
         "mean_abs_w", "reading_sigma", "bearing_sigma", "log_likelihood", "converged", "iterations", "seconds")
MAX_FLAG_LINES = 40
MAX_PANEL_FIGURES = 6


def _cell(v) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def table(rows: list[dict], drifted: dict) -> str:
    cols = [c for c in SHOWN if any(c in r for r in rows)]
    coef = sorted({c for r in rows for c in r if "_coef_" in c})      # a command map's, per command
    cols[cols.index("reading_sigma"):cols.index("reading_sigma")] = coef
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "<th>error</th>"
    body = []
    for r in rows:
        style = {"failed": ' style="background:#fdd"', "skipped": ' style="color:#666"'}.get(r["status"], "")
        if r.get("robot") in drifted and r["status"] != "failed":
            style = ' style="background:#ffe9c6"'
        body.append(f"<tr{style}>" + "".join(f"<td>{_cell(r.get(c))}</td>" for c in cols)
                    + f"<td>{_cell(r.get('error'))}</td></tr>")
    return f'<table class="t"><tr>{head}</tr>{"".join(body)}</table>'


def _scale_series(drift, robot: str, family: str, times: list[str]):
    """(session index, k, sd, flagged) of ``family``'s scale against the robot's first session."""
    pts = []
    for f in drift.families:
        if f["robot"] == robot and f["family"] == family and f["since"] == times[0] and f["time"] in times:
            pts.append((times.index(f["time"]), f["scale"], f["scale_std"], f["flagged"]))
    return sorted(pts)


def overview_figure(result) -> Figure | None:
    """Every robot's action-model scale against its first session over time; drifted robots in colour."""
    d = result.drift
    fig = Figure(figsize=(9, 4))
    ax = fig.add_subplot()
    drawn = False
    for i, robot in enumerate(sorted(d.series)):
        times = d.series[robot]["times"]
        for family in ("velocities", "command_map"):
            pts = _scale_series(d, robot, family, times)
            if not pts:
                continue
            x = [0] + [p[0] for p in pts]
            k = [1.0] + [p[1] for p in pts]
            bad = robot in d.drifted and family in d.drifted[robot]
            ax.plot(x, k, "-o", ms=3, lw=2 if bad else 0.8, color=f"C{i % 10}" if bad else "0.6",
                    label=robot if bad else None, zorder=3 if bad else 1)
            drawn = True
    if not drawn:
        return None
    ax.axhline(1, color="k", lw=0.5)
    ax.set_xlabel("session (0 = each robot's first)")
    ax.set_ylabel("action model scale vs first session")
    ax.set_title("action model over time, every robot (drifted ones in colour)")
    if d.drifted:
        ax.legend(fontsize=8)
    return fig


def robot_figure(result, robot: str) -> Figure:
    d = result.drift
    s = d.series[robot]
    times = s["times"]
    params = s["parameters"]
    x = np.arange(len(times))
    flagged_at = {}
    for f in d.flags:
        if f["robot"] == robot:
            flagged_at.setdefault(f["parameter"], set()).add(f["time"])
    fig = Figure(figsize=(12, 6.5))
    axes = fig.subplots(2, 2).ravel()

    ax = axes[0]
    for family, color in (("velocities", "C0"), ("command_map", "C0"), ("sensor", "C2")):
        pts = _scale_series(d, robot, family, times)
        if not pts:
            continue
        ax.errorbar([0] + [p[0] for p in pts], [1.0] + [p[1] for p in pts], yerr=[0.0] + [p[2] for p in pts],
                    fmt="-o", ms=4, capsize=3, color=color, label={"velocities": "velocity table",
                                                                   "command_map": "command map",
                                                                   "sensor": "sensor curve"}[family])
        bad = [p for p in pts if p[3]]
        if bad:
            ax.plot([p[0] for p in bad], [p[1] for p in bad], "o", ms=11, mfc="none", mec="red", mew=2,
                    label="drift beyond 3 sigma" if family != "sensor" else None)
    ax.axhline(1, color="k", lw=0.5)
    ax.set_title("scale against the first session (1 sigma)")
    ax.legend(fontsize=7)

    ax = axes[1]
    flagged = [n for n in params if n in flagged_at and params[n]["family"] in ("velocities", "command_map",
                                                                                  "effects")]
    flagged.sort(key=lambda n: -len(flagged_at[n]))
    shown = flagged[:MAX_PANEL_FIGURES]
    title = "figures that flagged (value, 1 sigma)"
    if not shown:
        shown = [n for n in params if params[n]["family"] == "command_map"][:MAX_PANEL_FIGURES]
        if not shown:                      # the actions that move most, to show the table is steady
            vel = [(n, np.nanmean(np.abs(np.array([np.nan if v is None else v for v in params[n]["values"]],
                                                    float)))) for n in params if params[n]["family"] == "velocities"]
            vel = [(n, v) for n, v in vel if np.isfinite(v)]
            shown = [n for n, _ in sorted(vel, key=lambda t: -t[1])[:4]]
        title = "figures over time (value, 1 sigma): none flagged"
    for j, n in enumerate(shown):
        v = np.array([np.nan if a is None else a for a in params[n]["values"]], float)
        e = np.array([np.nan if a is None else a for a in params[n]["std"]], float)
        ref = v[np.isfinite(v)][0] if np.isfinite(v).any() else 1.0
        ref = ref if ref != 0 else 1.0
        ax.errorbar(x + 0.04 * j, v / ref, yerr=np.nan_to_num(e / abs(ref)), fmt="-o", ms=3, capsize=2,
                    label=n, color=f"C{j}")
        hit = [i for i, t in enumerate(times) if t in flagged_at.get(n, ())]
        if hit:
            ax.plot(x[hit] + 0.04 * j, v[hit] / ref, "o", ms=10, mfc="none", mec="red", mew=2)
    ax.axhline(1, color="k", lw=0.5)
    ax.set_title(title + ", relative to the first value")
    if shown:
        ax.legend(fontsize=7)

    ax = axes[2]
    sensor = [n for n in params if params[n]["family"] == "sensor"]
    for j, n in enumerate(sensor):
        v = np.array([np.nan if a is None else a for a in params[n]["values"]], float)
        e = np.array([np.nan if a is None else a for a in params[n]["std"]], float)
        ax.errorbar(x + 0.04 * j, v, yerr=np.nan_to_num(e), fmt="-o", ms=3, capsize=2, label=n, color=f"C{j}")
        hit = [i for i, t in enumerate(times) if t in flagged_at.get(n, ())]
        if hit:
            ax.plot(x[hit] + 0.04 * j, v[hit], "o", ms=10, mfc="none", mec="red", mew=2)
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_title("sensor polynomial coefficients (1 sigma)")
    if sensor:
        ax.legend(fontsize=7)

    ax = axes[3]
    for j, n in enumerate(n for n in params if params[n]["family"] == "noise"):
        v = np.array([np.nan if a is None else a for a in params[n]["values"]], float)
        ref = v[np.isfinite(v)][0] if np.isfinite(v).any() and v[np.isfinite(v)][0] != 0 else 1.0
        ax.plot(x, v / ref, "-o", ms=3, label=n, color=f"C{j}")
    ax.axhline(1, color="k", lw=0.5)
    ax.set_title("noise levels relative to the first session (no std: not flagged)")
    ax.legend(fontsize=7)
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels(times, rotation=30, fontsize=7)
    fig.suptitle(robot + (" - drifted: " + ", ".join(d.drifted[robot]) if robot in d.drifted else ""))
    fig.tight_layout()
    return fig


def render(result) -> str:
    """The report as one self-contained HTML page."""
    d = result.drift
    c = result.counts
    style = ("body{font-family:sans-serif;margin:1.5em} table.t{border-collapse:collapse;font-size:12px}"
             "table.t td,table.t th{border:1px solid #ccc;padding:2px 5px;text-align:right}"
             "li{font-family:monospace}")
    opts = result.options
    thresholds = ", ".join(f"{f.replace('_', ' ')} {z:.2f}" for f, z in d.family_z.items())
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>casm-graph fleet</title><style>{style}</style>"
             + "</head><body>",
             "<h1>casm-graph fleet</h1>",
             (f"<p>{len(result.rows)} bundles under {html.escape(str(opts.get('root')))}: {c['ok']} calibrated, "
              f"{c['skipped']} skipped (complete), {c['failed']} failed; method {html.escape(str(opts.get('method')))}, "
              f"effects {html.escape(', '.join(opts.get('effects') or []) or 'none')}; "
              f"{result.seconds:.0f} s on {html.escape(result.scheduler)}.</p>"),
             "<h2>Drift</h2>",
             (f"<p>A figure is flagged between two sessions of a robot (consecutive, or the first against a later one) "
              f"when it changed by more than {d.z:g} times the combined posterior std and by at least "
              f"{100 * d.min_rel:g} %. A robot drifted in a family (velocity table, command map, sensor curve) when "
              f"the family's common scale moved beyond the family threshold ({html.escape(thresholds) or '-'} sigma: "
              f"{d.z:g}, or more where the fleet holds so many comparisons that {d.z:g} sigma would flag one by "
              f"chance), or when more of its actions flagged than chance allows.</p>")]
    lines = d.summary
    parts.append("<ul>" + "".join(f"<li>{html.escape(t)}</li>" for t in lines) + "</ul>" if lines
                 else "<p>No robot's model changed beyond its uncertainty.</p>")
    strongest = d.strongest_flags
    if strongest:
        parts.append(f"<details><summary>{len(strongest)} flagged figures (strongest per robot and figure)"
                     "</summary><ul>" + "".join(f"<li>{html.escape(f['text'])}</li>"
                                                for f in strongest[:MAX_FLAG_LINES]) + "</ul></details>")
    fig = overview_figure(result)
    if fig is not None:
        parts.append(png(fig))
    parts += ["<h2>The fleet</h2>", table(result.rows, d.drifted)]
    parts.append("<h2>Each robot over time</h2>")
    for robot in sorted(d.series):
        if len(d.series[robot]["times"]) < 2:
            continue
        parts += [f"<h3>{html.escape(robot)}</h3>", png(robot_figure(result, robot))]
    parts.append("</body></html>")
    return "\n".join(parts)
