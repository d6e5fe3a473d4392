"""Self-contained HTML reports: figures as embedded PNGs next to the numbers they show."""
from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from casm_graph.analysis.correlation import strongest
from casm_graph.analysis.predictive import words as predictive_words
from casm_graph.analysis.trace_measures import landmark_means, moving, normal_tail, speed_share, speed_trend, tail_share
from casm_graph.fit import residuals
from casm_graph.fit.result import Fit
from casm_graph.graph import augmented
from casm_graph.io.log import Log
from casm_graph.models.command_model import AXIS_WORDS, CommandModel, map_name
from casm_graph.models.effects.regional_motion_noise import determined, from_entry, variances
from casm_graph.models.effects.surface_friction import PATCH, SurfaceFriction
from casm_graph.models.model import Model
from casm_graph.models.velocity_table import VelocityTable
from casm_graph.report.signature import View, lead, ranked_pairs
from casm_graph.sim.aibo import true_reading

STYLE = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f0f0f0}img{max-width:100%}.bad{color:#b00}"""


def subplots(nrows: int = 1, ncols: int = 1, figsize=None, **kw):
    """A figure and its axes, made without pyplot so that reports never touch the caller's backend."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(nrows, ncols, **kw)


def png(fig) -> str:
    """An <img> tag holding ``fig`` as an embedded PNG."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def absent(ax, text: str) -> None:
    """Say on ``ax`` that the log does not measure what the panel would show."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()


def sensor_figure(log: Log, fit: Fit, truth: dict | None):
    m = fit.model
    d_obs = residuals.distances(fit.poses[log.obs_step], log)
    fig, ax = subplots(figsize=(7, 4))
    if not m.has("reading"):
        absent(ax, "no readings in this log (a bearing-only sensor):\nno sensor curve to learn")
        ax.set(title="Sensor model")
        return fig
    ok = ~np.isnan(log.obs_reading)
    ax.plot(d_obs[ok], log.obs_reading[ok], ".", ms=1, alpha=0.3, color="0.5", label="readings at fitted poses")
    lo, hi = m.distance_range
    d = np.linspace(lo, hi, 200)
    ax.plot(d, m.reading(d), "C0", lw=2, label="learned")
    if truth is not None and "camera" in truth.get("sensor_model", {}):
        ax.plot(d, true_reading(truth, d), "C3--", lw=2, label="true")
    ax.set(xlabel="distance (m)", ylabel="reading", title="Sensor model")
    ax.legend()
    return fig


def trajectory_figure(log: Log, poses: np.ndarray, std: np.ndarray, others: dict | None = None, ellipses: int = 60):
    """The estimated path with 2-sigma ellipses of its marginal x, y std, the truth when the log has it, the map."""
    fig, ax = subplots(figsize=(7, 6))
    if log.truth is not None:
        ax.plot(log.truth[:, 1], log.truth[:, 2], color="0.55", lw=1.2, label="truth")
    for i, (name, p) in enumerate((others or {}).items()):
        ax.plot(p[:, 0], p[:, 1], lw=0.6, color=f"C{i + 1}", label=name)
    ax.plot(poses[:, 0], poses[:, 1], "C0", lw=0.6, label="estimated")
    if np.isfinite(std[:, :2]).any():
        for k in np.linspace(0, len(poses) - 1, ellipses).astype(int):
            if np.isfinite(std[k, :2]).all():
                ax.add_patch(Ellipse((poses[k, 0], poses[k, 1]), 4 * std[k, 0], 4 * std[k, 1], fill=False,
                                     color="C0", lw=0.7, alpha=0.8))
        ax.plot([], [], "o", mfc="none", color="C0", label="2-sigma ellipses (x, y std)")
    ax.plot(log.landmark_xy[:, 0], log.landmark_xy[:, 1], "k^", ms=10, label="landmarks")
    for i, (x, y) in zip(log.landmark_ids, log.landmark_xy):
        ax.annotate(str(i), (x, y), textcoords="offset points", xytext=(6, 6))
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Trajectory on the map")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    return fig


def friction_figure(fit: Fit):
    """The fitted surface_friction field (share of speed lost against the grid's average floor, or against the floor
    off a patch, in %) with the trajectory over it."""
    e = fit.model.effects["surface_friction"]
    x0, y0, x1, y1 = e["extent"]
    gx, gy = np.meshgrid(np.linspace(x0, x1, 120), np.linspace(y0, y1, 90))
    field = SurfaceFriction()
    theta = augmented.theta_from_model([field], fit.model)        # restores the entry's order and extent too
    slow = field.slow(theta, np.column_stack([gx.ravel(), gy.ravel()]))
    slow = slow.reshape(gx.shape)
    lim = max(float(np.abs(slow).max()) * 100, 1.0)
    fig, ax = subplots(figsize=(7, 5))
    im = ax.pcolormesh(gx, gy, 100 * slow, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="auto")
    ax.plot(fit.poses[:, 0], fit.poses[:, 1], color="k", lw=0.3, alpha=0.4)
    against = "the floor off the patch" if field.order == PATCH else "the average floor"
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)", title=f"surface friction: speed lost (%) against {against}")
    fig.colorbar(im, ax=ax, shrink=0.8, label="% of speed lost")
    return fig


def regional_noise_figure(log: Log, fit: Fit, r_ref: float = 0.2, theta_ref: float = 0.1):
    """The regional_motion_noise map: per region the translation and rotation sigma of a reference step
    (``r_ref`` m, ``theta_ref`` rad) the fitted k's predict, the trajectory on top; undetermined regions grey."""
    e = fit.model.effects["regional_motion_noise"]
    regions, k = from_entry(e)
    vr, vt = variances(k, r_ref, theta_ref)
    x0, y0, x1, y1 = regions.extent
    nx, ny = regions.grid
    ok = determined(e)
    fig, axs = subplots(1, 2, figsize=(12, 4.6))
    for ax, v, unit, title in ((axs[0], 1000 * np.sqrt(vr), "mm", f"translation sigma of a {r_ref:g} m step"),
                               (axs[1], 1000 * np.sqrt(vt), "mrad", f"rotation sigma of a {r_ref:g} m, {theta_ref:g} rad step")):
        cmap = matplotlib.colormaps["viridis"].copy()
        cmap.set_bad("0.85")
        im = ax.imshow(np.where(ok, v, np.nan).reshape(ny, nx), origin="lower", extent=(x0, x1, y0, y1), cmap=cmap)
        fig.colorbar(im, ax=ax, label=unit, shrink=0.8)
        for g in range(regions.count):
            cx, cy = x0 + (g % nx + 0.5) * (x1 - x0) / nx, y0 + (g // nx + 0.5) * (y1 - y0) / ny
            ax.text(cx, cy, (f"{v[g]:.0f} {unit}" if ok[g] else "undetermined")
                    + f"\n{e.get('segments', [0] * regions.count)[g]} segments", ha="center", va="center",
                    fontsize=8, bbox={"facecolor": "w", "alpha": 0.7, "edgecolor": "none"})
        ax.plot(fit.poses[:, 0], fit.poses[:, 1], color="C3", lw=0.5)
        ax.plot(log.landmark_xy[:, 0], log.landmark_xy[:, 1], "k^", ms=6)
        ax.set(title=title, xlabel="x (m)", ylabel="y (m)", xlim=(x0, x1), ylim=(y0, y1))
        ax.set_aspect("equal")
    fig.tight_layout()
    return fig


def fitted_effects(log: Log, fit: Fit | None) -> list:
    """The effects the fit acted through (its ``hooked_effects``), instantiated for ``log``: the residuals a page
    shows go through its sensor effects."""
    return [cls(log) for cls in fit.notes.get("hooked_effects", ())] if fit is not None else []


def effect_panels(log: Log, fit: Fit) -> list[str]:
    """Report sections for the fitted effects that are better seen than read (the friction field on the floor, the
    motion noise by region)."""
    out = []
    e = fit.model.effects.get("surface_friction")
    if e and e.get("extent") is not None:
        out += ["<h2>Surface friction on the field</h2>", png(friction_figure(fit))]
    if "regional_motion_noise" in fit.model.effects:
        out += ["<h2>Motion noise by region (regional_motion_noise)</h2>", png(regional_noise_figure(log, fit))]
    return out


def fit_quality(cal) -> str:
    """The page's opening: how good the fit is, in units; the effects and their values; the run's record."""
    m, log, tr = cal.model, cal.log, cal.trajectory
    poses = np.column_stack([tr["x"], tr["y"], tr["theta"]])
    r, b = residuals.observation(poses[log.obs_step], log, m, fitted_effects(log, cal.fit))
    rows = []
    if m.action.std_summary() is not None:
        rows.append(m.action.std_summary())
    if m.reading_poly_cov is not None:
        d = np.linspace(*m.distance_range, 50)
        rows.append(("sensor curve std (median over distances seen)", f"{np.median(m.reading_std(d)):.3g} reading units"))
    for name, res, unit, sigma in (("reading", r, "reading units", m.reading_sigma), ("bearing", b, "rad", m.bearing_sigma)):
        ok = np.isfinite(res)
        if ok.sum() > 2:
            x = res[ok] - res[ok].mean()
            r1 = float(np.sum(x[1:] * x[:-1]) / max(np.sum(x * x), 1e-300))
            rows.append((f"{name} residuals", f"RMS {np.sqrt(np.mean(res[ok] ** 2)):.4g} {unit} (model sigma {sigma:.4g}); "
                                              f"lag-1 autocorrelation {r1:+.2f}, whiteness p {residuals.ljung_box(res[ok]):.2g}"))
    pos = np.sqrt(np.nanmean(tr["sx"] ** 2 + tr["sy"] ** 2)) if np.isfinite(tr["sx"]).any() else float("nan")
    rows.append(("trajectory position std (RMS)", f"{pos:.3f} m"))
    if log.truth is not None and len(log.truth) == len(poses):
        err = np.hypot(*(poses[:, :2] - log.truth[:, 1:3]).T)
        rows.append(("position RMS against truth.csv", f"{np.sqrt(np.mean(err ** 2)):.3f} m"))
    effects_std = m.fit.get("effects_std", {})
    for name, params in m.effects.items():
        vals = ", ".join(f"{k} {v:.4g}" + (f" &plusmn; {effects_std[name][k]:.2g}" if k in effects_std.get(name, {}) else "")
                         for k, v in params.items() if isinstance(v, (int, float)))
        rows.append((f"effect {html.escape(name)}", vals or "see model.json"))
    record = cal.model_json["fit"]
    rows += [("command", html.escape(str(record.get("command") or "(Python API)"))),
             ("casm-graph version", html.escape(str(record.get("version")))), ("log", html.escape(str(record.get("log"))))]
    body = "".join(f"<tr><th style='text-align:left'>{k}</th><td style='text-align:left'>{v}</td></tr>" for k, v in rows)
    return f"<h2>How good is the fit</h2><table>{body}</table>"


def residual_figure(log: Log, fit: Fit):
    """Motion residuals per step (the action model's velocities, no effects) and the sightings' residuals through
    the model's sensor effects; the distance from the truth when the log has it."""
    m = fit.model
    mot = residuals.step_motion(fit.poses, log, m)
    res = residuals.sighting_residuals(log, fit.poses[log.obs_step], m, fitted_effects(log, fit))
    r, b, d = res["reading"], res["bearing_residual"], res["distance"]
    truth = log.truth is not None and len(log.truth) == len(fit.poses)
    fig, axs = subplots(2, 3 if truth else 2, figsize=(14 if truth else 10, 6))
    t = log.t
    for i, (name, s) in enumerate([("forward (m)", 0), ("turn (rad)", 2)]):
        ax = axs[0, i]
        ax.plot(t, mot[:, s], ".", ms=1.5, alpha=0.4)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel="time (s)", ylabel=name, title=f"motion residual per step: {name.split()[0]}")
    ax = axs[1, 0]
    if m.has("reading"):
        ax.plot(d, r, ".", ms=1, alpha=0.3)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel="distance (m)", ylabel="reading residual", title=f"reading residual (sigma {m.noise_text('reading', '.3g')})")
    else:
        absent(ax, "no readings in this log (a bearing-only sensor)")
    ax = axs[1, 1]
    bb = b[~np.isnan(b)]
    if len(bb) and m.has("bearing"):
        sb = m.bearing_sigma
        lim = min(max(5 * sb, float(np.percentile(np.abs(bb), 99))), np.pi)     # the model's bell, and the tails
        ax.hist(np.clip(bb, -lim, lim), bins=60, range=(-lim, lim), density=True, alpha=0.6)
        x = np.linspace(-lim, lim, 200)
        ax.plot(x, np.exp(-0.5 * (x / sb) ** 2) / (sb * np.sqrt(2 * np.pi)), "C3", label="the model's noise")
        ax.set(xlabel="bearing residual (rad; the 1 % beyond at the edges)", title=f"bearing residual (sigma {sb:.3g})")
        ax.legend(fontsize=8)
    else:
        absent(ax, "no bearings in this log (a range-only sensor)")
    if truth:
        err = np.hypot(*(fit.poses[:, :2] - log.truth[:, 1:3]).T)
        axs[0, 2].plot(log.pose_times, err, lw=0.6)
        axs[0, 2].set(xlabel="time (s)", ylabel="position error (m)", title="distance from truth")
        axs[1, 2].set_axis_off()
    fig.tight_layout()
    return fig


def cost_figure(fit: Fit):
    fig, ax = subplots(figsize=(7, 3.5))
    cost = np.asarray(fit.cost)
    stages = np.asarray(fit.stages)
    for j, st in enumerate(dict.fromkeys(stages)):
        idx = np.flatnonzero(stages == st)
        ax.plot(idx + 1, cost[idx], "o-", ms=3, color=f"C{j}", label=f"{st} graph")
    if len(cost) and np.all(cost > 0):          # the EM methods' cost, -log p(O | model), may be negative
        ax.set_yscale("log")
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


def maps_figure(log: Log, fit: Fit, reference=None):
    """Learned forward-speed, sideways-speed (``vx, vy, w`` logs) and turn-rate maps over the commands run (and a
    reference map, if given), each at the other commands 0; a turn map with a term in v also at the median v."""
    cm = fit.model.command
    fig, axes = subplots(1, len(cm.maps), figsize=(5.5 * len(cm.maps), 4))
    for ax, (name, j, k, _) in zip(np.atleast_1d(axes), cm.maps):
        unit = "rad/s" if k == 2 else "m/s"
        c = log.controls[:, j]
        grid = np.linspace(c.min(), c.max(), 200)
        ctl = np.zeros((len(grid), log.controls.shape[1]))
        ctl[:, j] = grid
        ax.hist(c, bins=60, weights=log.dt, color="0.85", label="time at command (s, right axis)")
        ax2 = ax.twinx()
        ax2.plot(grid, grid, "k:", label="nominal (= command)")
        crossed = cm.cross_coefficient(name) is not None
        ax2.plot(grid, cm.velocities(ctl)[:, k], "C0", lw=2, label="learned" + (" at v = 0" if crossed else ""))
        if crossed:                          # the turn the forward command adds (unequal wheels)
            typical = float(np.median(log.controls[:, 0]))
            at = ctl.copy()
            at[:, 0] = typical
            ax2.plot(grid, cm.velocities(at)[:, k], "C2", lw=1.5, label=f"learned at v = {typical:.3g}")
        if reference is not None:
            ax2.plot(grid, reference.velocities(ctl)[:, k], "C3--", lw=2, label="fitted against truth")
        ax.set(xlabel=f"commanded {name} ({unit})", title=f"{AXIS_WORDS[k][0]} map")
        ax2.set_ylabel(f"actual {name} ({unit})")
        ax2.legend(loc="upper left", fontsize=8)
        ax.yaxis.set_visible(False)
    fig.tight_layout()
    return fig


def command_facts(m: Model) -> list[tuple]:
    """The command maps' coefficients, for the page's table of the fit."""
    cm = m.command

    def cross(name):
        term = cm.cross_coefficient(name)
        return "" if term is None else f"; {term[0]:+.4g} v/{cm.scale[0]:.3g}"

    return [(f"{map_name(k)} {name}(c)", ", ".join(f"{x:.4g}" for x in cm.coefficients(name)[0])
             + f" (powers of c/{cm.scale[j]:.3g})" + cross(name)) for name, j, k, _ in cm.maps]


@dataclass(frozen=True)
class ActionSection:
    """How the calibration page shows one kind of action model: its rows in the table of the fit, the section's
    title and its content (from the log, the fit, the simulator's truth model and a ground-truth evaluation)."""

    facts: Callable[[Model], list]
    title: str
    show: Callable[[Log, Fit, dict | None, dict | None], str]


SECTIONS = {VelocityTable.kind: ActionSection(lambda m: [], "Action table",
                                              lambda log, fit, truth, ev: velocity_table(fit, truth)),
            CommandModel.kind: ActionSection(command_facts, "Command maps", lambda log, fit, truth, ev: png(
                maps_figure(log, fit, ev["_vicon_model"] if ev is not None else None)))}


def calibration(path: Path, log: Log, fit: Fit, cal=None, truth: dict | None = None,
                evaluation: dict | None = None) -> None:
    """report.html of a calibration, any action model. ``cal`` (the Calibration) adds the opening table of fit
    quality, ``truth`` (a simulator's truth_model.json) the true values, ``evaluation`` (from
    :mod:`casm_graph.analysis.groundtruth`) the checks against a motion-capture truth."""
    m = fit.model
    f = m.fit
    section = SECTIONS[m.action.kind]
    facts = [("method", f.get("method")), ("iterations", f.get("iterations")),
             ("seconds", f.get("seconds")), ("converged", f.get("converged")),
             ("log-likelihood", f"{f.get('log_likelihood', float('nan')):.1f}"),
             ("steps", log.steps), ("observations", len(log.obs_t)),
             *([("sightings set aside", ", ".join(f"{k} {v}" for k, v in f["outliers_set_aside"].items())
                 if isinstance(f["outliers_set_aside"], dict) else f["outliers_set_aside"])]
               if "outliers_set_aside" in f else []),
             *section.facts(m),
             ("reading sigma", m.noise_text("reading")), ("bearing sigma (rad)", m.noise_text("bearing")),
             ("motion noise per step", ", ".join(f"{x:.4g}" for x in m.motion_noise)),
             ("sensor polynomial", m.curve_text()),
             ("distance range (m)", f"{m.distance_range[0]:.2f} to {m.distance_range[1]:.2f}")]
    if truth is not None:
        sm = truth.get("sensor_model", {})
        facts += [(f"true {k.replace('_', ' ')}", sm[k]) for k in ("reading_sigma", "bearing_sigma") if k in sm]
        if "camera" in sm and m.has("reading"):
            d = np.linspace(*m.distance_range, 200)
            facts.append(("sensor curve RMS vs truth", f"{np.sqrt(np.mean((m.reading(d) - true_reading(truth, d)) ** 2)):.3f}"))
    others = None
    if evaluation is not None:
        me, pr = evaluation["map_error"], evaluation["position_rms"]
        facts += [("turn map RMS vs truth fit", f"{me['w']['rms']:.4f} rad/s ({100 * me['w']['fraction']:.1f} % of range)"),
                  ("speed map RMS vs truth fit", f"{me['v']['rms']:.4f} m/s ({100 * me['v']['fraction']:.1f} % of range)")]
        facts += [(f"position RMS: {k.replace('_', ' ')}", f"{v:.3f} m") for k, v in pr.items()]
        others = {"identity-model graph": evaluation["_trajectories"]["identity_graph"]}
    info = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in facts)
    warn = ""
    if fit.notes.get("marginals_ridge"):
        warn = ("<p><b>Warning:</b> the fitted graph is nearly singular (a poor fit, or a log that cannot pin "
                f"the model down); the standard deviations were computed with a ridge of "
                f"{fit.notes['marginals_ridge']:g} x the largest information and are lower bounds.</p>")
    if not f.get("converged", True):
        warn += "<p><b>Warning:</b> the optimiser stopped before converging; check the cost per iteration.</p>"
    body = [f"<h1>casm-graph calibration</h1>{warn}", fit_quality(cal) if cal is not None else "",
            f"<h2>The fit</h2><table>{info}</table>", *effect_panels(log, fit),
            f"<h2>{section.title}</h2>", section.show(log, fit, truth, evaluation),
            "<h2>Sensor model</h2>", png(sensor_figure(log, fit, truth)),
            "<h2>Trajectory</h2>", png(trajectory_figure(log, fit.poses, fit.pose_std, others)),
            "<h2>Residuals</h2>", png(residual_figure(log, fit)),
            "<h2>Cost per iteration</h2>", png(cost_figure(fit))]
    path.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>casm-graph calibration</title>"
                    f"<style>{STYLE}</style></head><body>{''.join(body)}</body></html>")


# ----------------------------------------------------------------------------- diagnosis
def _binned(x, y, bins=12):
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    g = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    n = np.bincount(g, minlength=len(edges) - 1)
    ok = n > 1
    m = np.bincount(g, weights=y, minlength=len(n))[ok] / n[ok]
    v = np.bincount(g, weights=y * y, minlength=len(n))[ok] / n[ok] - m ** 2
    c = 0.5 * (edges[:-1] + edges[1:])[ok]
    return c, m, 2 * np.sqrt(np.maximum(v, 0) / n[ok])


def covariate_panels(diag, top: int = 6, pairs=None):
    """Residual-covariate dependences (``pairs`` of channel and test, else the ``top`` strongest): residuals, binned
    means and their 2-SE bars."""
    pairs = list(ranked_pairs(diag, top=top) if pairs is None else pairs)
    fig, axes = subplots(int(np.ceil(len(pairs) / 3)) or 1, 3, figsize=(13, 3.4 * max(1, int(np.ceil(len(pairs) / 3)))),
                             squeeze=False)
    rng = np.random.default_rng(0)
    for ax, (ch, c) in zip(axes.ravel(), pairs):
        data = diag.residuals[ch]
        x, y = data.covariates[c["name"]], data.residual
        ok = np.isfinite(x) & np.isfinite(y)
        x, y = x[ok], y[ok]
        idx = rng.choice(len(x), min(len(x), 3000), replace=False)
        ax.plot(x[idx], y[idx], ".", ms=1.5, alpha=0.3, color="0.5")
        yv = np.abs(y - np.median(y)) if c["kind"] == "spread" else y
        cx, m, se = _binned(x, yv)
        ax.errorbar(cx, m, se, color="C3", lw=2, capsize=2)
        ax.axhline(0, color="k", lw=0.5)
        lo, hi = np.quantile(y, [0.01, 0.99])
        ax.set_ylim(lo, hi)
        ax.set(xlabel=c["name"], ylabel=f"{ch} residual (sigmas)",
               title=f"{ch} {c['kind']} vs {c['name']}: omega2 {c['strength']:.3f}, p {c['p']:.0e}"
                     + (f" ({c['lead_strength']:.3f} {c['lead']:.2f} s later: the loop)" if c["kind"] == "feedback" else ""))
        ax.title.set_fontsize(9)
    for ax in axes.ravel()[len(pairs):]:
        ax.axis("off")
    fig.tight_layout()
    return fig


def field_heatmap(diag):
    """Mean whitened motion residual by where on the field the step began."""
    fig, axes = subplots(1, 3, figsize=(13, 3.4))
    for ax, ch in zip(axes, ("forward", "lateral", "turn")):
        d = diag.residuals[ch]
        hb = ax.hexbin(d.covariates["x"], d.covariates["y"], C=d.residual, gridsize=18, reduce_C_function=np.mean,
                       cmap="RdBu_r", vmin=-1, vmax=1, mincnt=20)
        ax.set(aspect="equal", title=f"{ch} residual by position", xlabel="x (m)", ylabel="y (m)")
        fig.colorbar(hb, ax=ax, shrink=0.8)
    fig.tight_layout()
    return fig


def _landmark_axis(ax, diag) -> None:
    """Mean sighting residual per landmark, each channel's, with 2-SE bars."""
    for k, ch in enumerate(c for c in ("reading", "bearing") if c in diag.residuals):
        ids, m, se = landmark_means(diag, ch)
        ax.errorbar(np.arange(len(ids)) + 0.15 * k, m, 2 * se, fmt="o", label=ch)
        ax.set_xticks(np.arange(len(ids)), [str(int(i)) for i in ids])
    ax.axhline(0, color="k", lw=0.5)
    ax.set(xlabel="landmark", ylabel="mean residual (sigmas)", title="per landmark")
    ax.legend(fontsize=8)


def landmark_figure(diag):
    """The sightings' mean residual per landmark: a misplaced landmark's stand off zero, the others' not."""
    fig, ax = subplots(figsize=(6.5, 3.4))
    _landmark_axis(ax, diag)
    fig.tight_layout()
    return fig


def tails_figure(diag):
    """The sightings' whitened residuals against the normal distribution the model assumes (log counts): sightings
    that follow no landmark sit in the tails, many sigmas out."""
    chans = [c for c in ("reading", "bearing") if c in diag.residuals]
    fig, axes = subplots(1, len(chans), figsize=(6.5 * len(chans), 3.4), squeeze=False)
    for ax, ch in zip(axes[0], chans):
        r = diag.residuals[ch].residual
        r = r[np.isfinite(r)]
        edges = np.linspace(-8, 8, 65)
        counts, _ = np.histogram(np.clip(r, -8, 8), edges)
        mid = 0.5 * (edges[:-1] + edges[1:])
        ax.bar(mid, counts, width=edges[1] - edges[0], color="0.6", label="residuals (beyond 8 in the end bins)")
        normal = len(r) * (edges[1] - edges[0]) * np.exp(-0.5 * mid ** 2) / np.sqrt(2 * np.pi)
        ax.plot(mid, normal, color="C3", lw=1.5, label="normal")
        ax.set_yscale("log")
        ax.set_ylim(0.5, None)
        ax.set(xlabel=f"{ch} residual (sigmas)", ylabel="sightings",
               title=f"{ch}: {100 * tail_share(r):.2f} % beyond 4 sigmas (normal: {100 * normal_tail():.3f} %)")
        ax.legend(fontsize=8)
    if diag.set_aside:
        fig.suptitle(f"{diag.set_aside} further sighting(s) set aside before the fit as gross outliers", fontsize=9)
    fig.tight_layout()
    return fig


def speed_figure(diag, bins: int = 12):
    """The share of its modelled motion the robot achieved over time, per motion axis, with 2-SE bars: a fading
    battery's runs fall short more and more."""
    chans = moving(diag)
    fig, ax = subplots(figsize=(13, 3.4))
    for k, ch in enumerate(chans):
        d = diag.residuals[ch]
        edges = np.linspace(np.nanmin(d.time), np.nanmax(d.time) + 1e-9, bins + 1)
        share, se = speed_share(d, edges, diag.options.trend_block)
        mid = 0.5 * (edges[:-1] + edges[1:]) / 60
        rate, t = speed_trend(d, diag.options.trend_block, diag.options.trend_memory)
        ax.errorbar(mid + 0.05 * (k - 1) * (mid[1] - mid[0]), 100 * share, 200 * se, fmt="o-", ms=3, capsize=2,
                    label=f"{ch}: {100 * rate:+.2f} % per minute (t {t:.1f})")
    ax.axhline(100, color="k", lw=0.5)
    ax.set(xlabel="time (min)", ylabel="% of the modelled motion achieved",
           title="the motion achieved against the model's, over time (a fade: falling)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


VIEW_WORDS = {
    "covariates": "the residuals against what it explains, strongest dependence first (binned means with 2-SE bars)",
    "correlation": "the motion residuals against the change of the model's velocity over the second before and after, "
                   "and the sightings' residual autocorrelation (outside the grey band: more than white residuals show)",
    "field": "the motion residuals by where on the field the step began (red: the robot went further than the "
             "model; blue: less)",
    "landmarks": "the sightings' mean residual per landmark (landmarks whose sightings stand off zero: the map is "
                 "wrong somewhere; the path takes part of one landmark's move, which then shows on its neighbours "
                 "too, so the fit, not this panel, says which one moved)",
    "tails": "the sightings' residuals against the normal distribution the model assumes (log scale)",
    "speed": "the share of its modelled motion the robot achieved, over time"}


def view_figure(diag, view: View):
    """The figure of one signature view (:mod:`casm_graph.report.signature`)."""
    return {"covariates": lambda: covariate_panels(diag, pairs=view.pairs),
            "correlation": lambda: correlation_figure(diag), "field": lambda: field_heatmap(diag),
            "landmarks": lambda: landmark_figure(diag), "tails": lambda: tails_figure(diag),
            "speed": lambda: speed_figure(diag)}[view.kind]()


def _trace_html(diag, views: list[View]) -> str:
    """The verdict's and its look-alikes' views, each with what to look for."""
    return "".join(f"<p><b>{html.escape(', '.join(v.effects))}</b>: {VIEW_WORDS[v.kind]}.</p>"
                   f"{png(view_figure(diag, v))}" for v in views)


def group_panels(diag):
    """Mean residual per landmark (sensor channels) and per action (motion channels), with 2-SE bars."""
    fig, axes = subplots(1, 2, figsize=(13, 3.4), gridspec_kw={"width_ratios": [1, 3]})
    _landmark_axis(axes[0], diag)
    actions = "action" in diag.residuals["forward"].covariates       # continuous commands have none
    for k, ch in enumerate(("forward", "lateral", "turn") if actions else ()):
        d = diag.residuals[ch]
        a = d.covariates["action"]
        ids = np.unique(a)
        m = [d.residual[a == i].mean() * np.sqrt((a == i).sum()) for i in ids]
        axes[1].plot(np.arange(len(ids)), m, "o-", ms=3, label=ch)
        axes[1].set_xticks(np.arange(len(ids)), [str(int(i)) for i in ids], fontsize=6)
    axes[1].axhline(0, color="k", lw=0.5)
    axes[1].set(xlabel="action", ylabel="mean x sqrt(n) (z-score)", title="per action")
    if actions:
        axes[1].legend(fontsize=8)
    else:
        axes[1].set_title("per action (continuous commands: no actions)")
    fig.tight_layout()
    return fig


def time_panel(diag):
    """Residuals over time: a moving mean per channel."""
    fig, ax = subplots(figsize=(13, 3.2))
    for ch, d in diag.residuals.items():
        order = np.argsort(d.time)
        t, r = d.time[order], d.residual[order]
        w = max(len(r) // 60, 1)
        mm = np.convolve(r, np.ones(w) / w, mode="valid") * np.sqrt(w)
        ax.plot(t[w - 1:] / 60, mm, lw=1, label=ch)
    ax.axhline(0, color="k", lw=0.5)
    ax.set(xlabel="time (min)", ylabel="moving mean x sqrt(window)", title="residuals over time (z-scores; |z| > 3 is unusual)")
    ax.legend(fontsize=8, ncol=5)
    return fig


def correlation_figure(diag):
    """resid-style panels: each motion axis's residual against the change of its commanded velocity, and the
    sightings' residual autocorrelation, each with its 99 % band for white residuals."""
    corr = diag.correlation
    fig, axes = subplots(1, 2, figsize=(13, 3.4))
    for ax, kind in zip(axes, ("cross", "auto")):
        band = 0.0
        for ch, rec in corr.items():
            if rec["series"] == kind:
                ax.plot(np.asarray(rec["lags"]) * rec["step_s"], rec["values"], ".-", ms=3, lw=1, label=ch)
                band = max(band, rec["band"])
        ax.axhspan(-band, band, color="0.85", zorder=0, label="99 % band (white)")
        ax.axhline(0, color="k", lw=0.5)
        ax.legend(fontsize=7)
    axes[0].set(xlabel="lag (s): the velocity changed this long before the residual", ylabel="correlation",
                title="motion residual vs change of the model's velocity on its axis")
    axes[1].set(xlabel="lag (s)", ylabel="autocorrelation", title="sighting residual autocorrelation")
    fig.tight_layout()
    return fig


def predictive_figure(diag):
    """Open-loop prediction error per horizon and channel (the earlier diagnosis' dashed when given)."""
    pred = diag.predictive
    chans = list(pred["channels"])
    before = (diag.before_after or {}).get("predictive") or {}
    fig, axes = subplots(1, len(chans), figsize=(6.5 * len(chans), 3.2), squeeze=False)
    for ax, ch in zip(axes[0], chans):
        if ch in before.get("channels", {}):
            ax.plot(before["horizons_s"], before["channels"][ch][0], "o--", color="0.5", label="before")
        ax.plot(pred["horizons_s"], pred["channels"][ch], "o-", color="C0", label="this model")
        ax.set(xlabel="horizon (s): the model run open-loop this long", ylabel="error (robust scale, channel unit)",
               title=f"{ch}: predicted sightings against measured")
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def before_after_figure(diag):
    """Before and after: each channel's residual RMS (relative to before) and the earlier diagnosis' strongest
    covariate's share of the residual variance then and now."""
    rows = diag.before_after["channels"]
    names = [ch for ch, r in rows.items() if None not in r["rms_raw"]]
    fig, axes = subplots(1, 2, figsize=(13, 3.4))
    x = np.arange(len(names))
    ratio = [rows[ch]["rms_raw"][1] / rows[ch]["rms_raw"][0] if rows[ch]["rms_raw"][0] else np.nan for ch in names]
    axes[0].bar(x, ratio, color=["0.6" if abs(r - 1) < 0.02 else "C2" if r < 1 else "C3" for r in ratio])
    axes[0].axhline(1, color="k", lw=0.8)
    axes[0].set_xticks(x, names)
    axes[0].set(ylabel="residual RMS, after / before", title="error per channel (below 1: it fell; grey: within 2 %)")
    cov = [(ch, rows[ch]["covariate"]) for ch in names if rows[ch].get("covariate")
           and None not in rows[ch]["covariate"]["strength"]]
    xs = np.arange(len(cov))
    axes[1].bar(xs - 0.2, [100 * c["strength"][0] for _, c in cov], 0.4, label="before")
    axes[1].bar(xs + 0.2, [100 * c["strength"][1] for _, c in cov], 0.4, label="after")
    axes[1].set_xticks(xs, [f"{ch}\n{c['kind']} vs {c['name']}" for ch, c in cov], fontsize=7)
    axes[1].set(ylabel="% of residual variance", title="the earlier strongest dependence, per channel")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    return fig


def _before_after_html(diag) -> str:
    ba = diag.before_after
    if not ba:
        return ""
    e = html.escape
    (v0, v1), (l0, l1), (s0, s1) = ba["verdict"], ba["log_likelihood"], ba["sightings_set_aside"]
    fmt = (lambda v: "" if v is None else f"{v:.4g}")
    rows = "".join(
        f"<tr><td style='text-align:left'>{e(ch)}</td><td>{fmt(r['rms'][0])} &rarr; {fmt(r['rms'][1])}</td>"
        f"<td>{fmt(r['rms_raw'][0])} &rarr; {fmt(r['rms_raw'][1])}</td>"
        + (f"<td style='text-align:left'>{e(r['covariate']['kind'])} vs {e(r['covariate']['name'])}: "
           f"{fmt(r['covariate']['strength'][0])} &rarr; {fmt(r['covariate']['strength'][1])}</td>"
           if r.get("covariate") else "<td></td>") + "</tr>"
        for ch, r in ba["channels"].items())
    return (f"<h2>Before and after</h2><p>Against the earlier diagnosis: verdict <code>{e(str(v0))}</code> &rarr; "
            f"<code>{e(str(v1))}</code>; effects {e(', '.join(ba['effects'][0]) or 'none')} &rarr; "
            f"{e(', '.join(ba['effects'][1]) or 'none')}; refitted log-likelihood {fmt(l0)} &rarr; {fmt(l1)} "
            f"(comparable when the same sightings were set aside: {s0} &rarr; {s1}).</p>"
            "<table><tr><th>channel</th><th>whitened RMS</th><th>raw RMS</th><th>earlier strongest covariate "
            f"(omega squared)</th></tr>{rows}</table>{png(before_after_figure(diag))}")


def _failure_panels(diag, shown: set) -> str:
    """Covariate panels and residual correlation, the one with the stronger structure first (correlation not again
    when the ``shown`` views hold it)."""
    parts = [("covariates", png(covariate_panels(diag)))]
    if diag.correlation and "correlation" not in shown:
        ch, ratio = strongest(diag.correlation)
        top = max((c["strength"] for r in diag.channels.values() for c in r["covariates"]), default=0.0)
        text = (f"<p>Residual correlation over time (strongest: {html.escape(ch)}, {ratio:.1f} times the 99 % "
                f"band of white residuals).</p>{png(correlation_figure(diag))}")
        # a dependence on a covariate explaining under 1 % of the variance is weaker than time structure
        # well outside its band: then time structure comes first
        parts.insert(0 if (top < 0.01 and ratio > 2) else 1, ("correlation", text))
    if diag.predictive.get("channels") and len(diag.predictive["horizons_s"]) > 1:
        parts.append(("predictive", f"<p>{html.escape(predictive_words(diag.predictive))} A model that lacks an "
                                    f"effect of the motion predicts worse the longer it runs on its own.</p>"
                                    f"{png(predictive_figure(diag))}"))
    return "".join(p for _, p in parts)


def diagnosis(path: Path, log: Log, diag) -> None:
    """DIAG/report.html: the verdict in words, the tables, then the panels strongest first."""
    e = html.escape
    rows = "".join(
        f"<tr><td style='text-align:left'>{ch}</td><td>{r['rms']:.3f}</td><td>{r['whiteness_p']:.2g}</td>"
        + "".join(f"<td>{c['name']} ({c['kind']}) {c['strength']:.3f}</td>" for c in r["covariates"][:3]) + "</tr>"
        for ch, r in diag.channels.items())
    cands = "".join(
        f"<tr><td style='text-align:left'>{c.spec}</td><td>{c.channel}</td><td>{'&asymp; ' if c.screened else ''}"
        f"{c.delta_bic:.1f}"
        + (f"<br><small>by order: {', '.join(f'{k}: {v:.1f}' for k, v in sorted(c.orders.items()))}</small>"
           if c.orders else "") + "</td>"
        f"<td>{c.heldout_nll_drop:.1f}</td><td>{'' if not np.isfinite(c.change) else f'{c.change:.3f}'}</td>"
        f"<td style='text-align:left'>{e(', '.join(f'{k}={v:.4g}' for k, v in c.parameters.items() if isinstance(v, (int, float))))}</td>"
        f"<td style='text-align:left'>"
        + (f"<b>Set aside, not physical:</b> {e(c.implausible)}. " if c.implausible else "")
        + f"{e(c.explanation)}</td></tr>" for c in diag.candidates)
    skipped = "".join(f"<li>{e(k)}: {e(v)}</li>" for k, v in diag.skipped.items())
    views = lead(diag)
    shown = {v.kind for v in views}
    trace = (f"<h2>The trace of {e(diag.verdict)}</h2><p>What in the residuals points to it"
             f"{' and to its look-alikes' if len(views) > 1 else ''}:</p>{_trace_html(diag, views)}") if views else ""
    sections = [f"<h2>Where the model fails</h2>{_failure_panels(diag, shown)}",
                "" if "field" in shown else f"<h2>On the field</h2>{png(field_heatmap(diag))}"]
    on_field = bool(diag.structure) and diag.structure[0]["name"] in ("place", "x", "y")   # where: the map first
    body = f"""<!doctype html><html><head><meta charset="utf-8"><title>casm-graph diagnosis</title>
<style>{STYLE}</style></head><body>
<h1>Diagnosis: <code>{e(diag.verdict)}</code></h1>
{''.join(f'<p>{e(w)}</p>' for w in diag.words)}
{trace}
<h2>Channels</h2><p>Whitened residuals (1.0 = as noisy as the model says). Whiteness: Ljung-Box p.
Strength: omega squared, the share of residual variance a covariate explains (mean or spread).</p>
<table><tr><th>channel</th><th>rms</th><th>whiteness p</th><th>strongest</th><th>2nd</th><th>3rd</th></tr>{rows}</table>
<h2>Candidate effects</h2><p>Sorted by delta BIC (negative favours the effect); held-out: gain in log-likelihood of
time blocks hidden from the fit. A family (<code>NAME:ORDER</code>) shows the member BIC kept and every member's delta BIC.
A delta BIC marked &asymp; is the score test's prediction: the candidate was not fitted, its predicted gain
being too small a share of its BIC penalty. Sightings moved: the RMS change the candidate's fit makes to the predicted
readings and bearings, in their sigmas (blank where the candidate has no fitted prediction).</p>
<table><tr><th>effect</th><th>channel</th><th>delta BIC</th><th>held-out gain</th><th>sightings moved</th><th>fitted</th>
<th>physics</th></tr>{cands}</table>
{f'<p>Not applicable to this log:</p><ul>{skipped}</ul>' if skipped else ''}
{_before_after_html(diag)}
{''.join(sections if not on_field else sections[::-1])}
<h2>Per landmark and per action</h2>{png(group_panels(diag))}
<h2>Over time</h2>{png(time_panel(diag))}
<p style="color:#777">{diag.seconds:.1f} s</p></body></html>"""
    Path(path).write_text(body)
