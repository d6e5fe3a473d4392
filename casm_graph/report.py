"""Self-contained HTML reports: figures as embedded PNGs next to the numbers they show."""
from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from . import graph as G  # noqa: E402
from . import residuals  # noqa: E402
from .log import Log  # noqa: E402
from .methods.base import Fit  # noqa: E402

STYLE = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f0f0f0}img{max-width:100%}.bad{color:#b00}"""


def png(fig) -> str:
    """An <img> tag holding ``fig`` as an embedded PNG (the figure is closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def sensor_figure(log: Log, fit: Fit, truth: dict | None):
    m = fit.model
    d_obs = residuals.distances(fit.poses[log.obs_step], log)
    fig, ax = plt.subplots(figsize=(7, 4))
    ok = ~np.isnan(log.obs_reading)
    ax.plot(d_obs[ok], log.obs_reading[ok], ".", ms=1, alpha=0.3, color="0.5", label="readings at fitted poses")
    lo, hi = m.distance_range
    d = np.linspace(lo, hi, 200)
    ax.plot(d, m.reading(d), "C0", lw=2, label="learned")
    if truth is not None and "camera" in truth.get("sensor_model", {}):
        from .simulate import true_reading
        ax.plot(d, true_reading(truth, d), "C3--", lw=2, label="true")
    ax.set(xlabel="distance (m)", ylabel="reading", title="Sensor model")
    ax.legend()
    return fig


def trajectory_figure(log: Log, fit: Fit, std: np.ndarray):
    fig, ax = plt.subplots(figsize=(7, 6))
    p = fit.poses
    ax.plot(p[:, 0], p[:, 1], "C0", lw=0.6, label="estimated")
    if not np.all(np.isnan(std[:, 0])):
        band = np.hypot(std[:, 0], std[:, 1])
        sc = ax.scatter(p[::30, 0], p[::30, 1], c=band[::30], s=6, cmap="viridis", zorder=3)
        fig.colorbar(sc, ax=ax, label="position std (m)")
    ax.plot(log.landmark_xy[:, 0], log.landmark_xy[:, 1], "k^", ms=10, label="landmarks")
    for i, (x, y) in zip(log.landmark_ids, log.landmark_xy):
        ax.annotate(str(i), (x, y), textcoords="offset points", xytext=(6, 6))
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Trajectory on the map")
    ax.set_aspect("equal")
    ax.legend(loc="upper right")
    return fig


def residual_figure(log: Log, fit: Fit):
    m = fit.model
    lay = G.layout(log, m, 1)
    mot = residuals.motion(fit.poses, lay, m)
    r, b = residuals.observation(fit.poses[log.obs_step], log, m)
    d = residuals.distances(fit.poses[log.obs_step], log)
    fig, axs = plt.subplots(2, 2, figsize=(10, 6))
    t = log.t
    for i, (name, s) in enumerate([("forward (m)", 0), ("turn (rad)", 2)]):
        ax = axs[0, i]
        ax.plot(t, mot[:, s], ",", alpha=0.4)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel="time (s)", ylabel=name, title=f"motion residual: {name.split()[0]}")
    ax = axs[1, 0]
    ax.plot(d, r, ".", ms=1, alpha=0.3)
    ax.axhline(0, color="k", lw=0.5)
    ax.set(xlabel="distance (m)", ylabel="reading residual", title=f"reading residual (sigma {m.reading_sigma:.3g})")
    ax = axs[1, 1]
    bb = b[~np.isnan(b)]
    ax.hist(bb, bins=60, density=True, alpha=0.6)
    x = np.linspace(-np.pi, np.pi, 200)
    s = m.bearing_sigma
    ax.plot(x, np.exp(-0.5 * (x / s) ** 2) / (s * np.sqrt(2 * np.pi)), "C3")
    ax.set(xlabel="bearing residual (rad)", title=f"bearing residual (sigma {s:.3g})")
    fig.tight_layout()
    return fig


def cost_figure(fit: Fit):
    fig, ax = plt.subplots(figsize=(7, 3.5))
    cost = np.asarray(fit.cost)
    stages = np.asarray(fit.stages)
    for j, st in enumerate(dict.fromkeys(stages)):
        idx = np.flatnonzero(stages == st)
        ax.semilogy(idx + 1, cost[idx], "o-", ms=3, color=f"C{j}", label=f"{st} graph")
    ax.set(xlabel="iteration", ylabel="cost (half chi-square)", title="Cost per iteration")
    ax.legend()
    return fig


def velocity_table(fit: Fit, truth: dict | None) -> str:
    m = fit.model
    tv = None
    if truth is not None:
        tab = truth.get("action_model", {}).get("velocities", {})
        if all(str(int(a)) in tab for a in m.action_ids):
            tv = np.array([tab[str(int(a))] for a in m.action_ids])
    head = "<tr><th>action</th><th>vx (m/s)</th><th>vy (m/s)</th><th>w (rad/s)</th>"
    head += "<th>true vx</th><th>true vy</th><th>true w</th></tr>" if tv is not None else "</tr>"
    rows = []
    std = m.velocity_std if m.velocity_std is not None else np.full_like(m.velocities, np.nan)
    for i, a in enumerate(m.action_ids):
        cells = [f"{v:+.3f} &plusmn; {s:.3f}" for v, s in zip(m.velocities[i], std[i])]
        if tv is not None:
            cells += [f"{v:+.3f}" for v in tv[i]]
        rows.append(f"<tr><td>{int(a)}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    summary = ""
    if tv is not None:
        rms = np.sqrt(np.mean((m.velocities - tv) ** 2, axis=0))
        summary = (f"<p>RMS error against the simulator's table: vx {1000 * rms[0]:.1f} mm/s, "
                   f"vy {1000 * rms[1]:.1f} mm/s, w {rms[2]:.4f} rad/s.</p>")
    return summary + f"<table>{head}{''.join(rows)}</table>"


def calibration(path: Path, log: Log, fit: Fit, std: np.ndarray, truth: dict | None) -> None:
    """report.html of a calibration run."""
    m = fit.model
    f = m.fit
    facts = [("method", f.get("method")), ("iterations", f.get("iterations")),
             ("seconds", f.get("seconds")), ("converged", f.get("converged")),
             ("log-likelihood", f"{f.get('log_likelihood', float('nan')):.1f}"),
             ("steps", log.steps), ("observations", len(log.obs_t)),
             ("reading sigma", f"{m.reading_sigma:.4g}"), ("bearing sigma (rad)", f"{m.bearing_sigma:.4g}"),
             ("motion noise per step", ", ".join(f"{x:.4g}" for x in m.motion_noise)),
             ("sensor polynomial", ", ".join(f"{c:.5g}" for c in m.reading_poly)),
             ("distance range (m)", f"{m.distance_range[0]:.2f} to {m.distance_range[1]:.2f}")]
    if truth is not None:
        sm = truth.get("sensor_model", {})
        facts += [("true reading sigma", sm.get("reading_sigma")), ("true bearing sigma", sm.get("bearing_sigma"))]
        if "camera" in sm:
            from .simulate import true_reading
            d = np.linspace(*m.distance_range, 200)
            facts.append(("sensor curve RMS vs truth", f"{np.sqrt(np.mean((m.reading(d) - true_reading(truth, d)) ** 2)):.3f}"))
    info = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in facts)
    body = [f"<h1>casm-graph calibration</h1><table>{info}</table>",
            "<h2>Sensor model</h2>", png(sensor_figure(log, fit, truth)),
            "<h2>Cost per iteration</h2>", png(cost_figure(fit)),
            "<h2>Trajectory</h2>", png(trajectory_figure(log, fit, std)),
            "<h2>Residuals</h2>", png(residual_figure(log, fit)),
            "<h2>Action table</h2>", velocity_table(fit, truth)]
    path.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>casm-graph calibration</title>"
                    f"<style>{STYLE}</style></head><body>{''.join(body)}</body></html>")
