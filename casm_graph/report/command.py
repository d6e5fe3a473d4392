"""report.html of a continuous-command calibration: command maps, sensor curve, trajectory, residuals."""
from __future__ import annotations

import html
from pathlib import Path

import matplotlib
import numpy as np

from casm_graph.fit import continuous
from casm_graph.fit.result import Fit
from casm_graph.io.log import Log
from casm_graph.models.effects.regional_motion_noise import determined, from_entry, variances
from casm_graph.report.pages import (STYLE, cost_figure, effect_panels, fit_quality, png, sensor_figure, subplots,
                                     trajectory_figure)


def maps_figure(log: Log, fit: Fit, reference=None):
    """Learned forward-speed and turn-rate maps over the commands run (and a reference map, if given)."""
    cm = fit.model.command
    fig, axes = subplots(1, 2, figsize=(11, 4))
    for ax, j, name, unit in ((axes[0], 0, "v", "m/s"), (axes[1], 1, "w", "rad/s")):
        c = log.controls[:, j]
        grid = np.linspace(c.min(), c.max(), 200)
        ctl = np.zeros((len(grid), 2))
        ctl[:, j] = grid
        k = 0 if j == 0 else 2
        ax.hist(c, bins=60, weights=log.dt, color="0.85", label="time at command (s, right axis)")
        ax2 = ax.twinx()
        ax2.plot(grid, grid, "k:", label="nominal (= command)")
        ax2.plot(grid, cm.velocities(ctl)[:, k], "C0", lw=2, label="learned")
        if reference is not None:
            ax2.plot(grid, reference.velocities(ctl)[:, k], "C3--", lw=2, label="fitted against truth")
        ax.set(xlabel=f"commanded {name} ({unit})", title=f"{'forward speed' if j == 0 else 'turn rate'} map")
        ax2.set_ylabel(f"actual {name} ({unit})")
        ax2.legend(loc="upper left", fontsize=8)
        ax.yaxis.set_visible(False)
    fig.tight_layout()
    return fig


def residual_figure(log: Log, fit: Fit):
    """Reading and bearing residuals under the fitted model, its lens and hooked sensor effects included."""
    effects = [cls(log) for cls in fit.notes.get("hooked_effects", ())]
    res = continuous.sighting_residuals(log, fit.poses[log.obs_step], fit.model, effects)
    r, b, d = res["reading"], res["bearing_residual"], res["distance"]
    fig, axs = subplots(1, 3, figsize=(13, 3.6))
    axs[0].plot(d, r, ".", ms=2, alpha=0.4)
    axs[0].set(xlabel="distance (m)", ylabel="reading residual", title=f"reading (sigma {fit.model.noise_text('reading', '.3g')})")
    axs[1].plot(log.obs_t, b, ".", ms=2, alpha=0.4)
    axs[1].set(xlabel="time (s)", ylabel="bearing residual (rad)",
               title=f"bearing (sigma {fit.model.noise_text('bearing', '.3g')})")
    for ax, channel in zip(axs[:2], ("reading", "bearing")):
        if not fit.model.has(channel):
            ax.set_title(f"{channel} (not measured)")
            ax.text(0.5, 0.5, f"this log has no {channel}s", ha="center", va="center", transform=ax.transAxes,
                    backgroundcolor="white")
    if log.truth is not None:
        err = np.hypot(*(fit.poses[:, :2] - log.truth[:, 1:3]).T)
        axs[2].plot(log.pose_times, err, lw=0.6)
        axs[2].set(xlabel="time (s)", ylabel="position error (m)", title="distance from truth")
    else:
        axs[2].axis("off")
    for ax in axs[:2]:
        ax.axhline(0, color="k", lw=0.5)
    fig.tight_layout()
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


def calibration(path: Path, log: Log, fit: Fit, evaluation: dict | None = None, cal=None) -> None:
    """report.html of a continuous-command run; ``evaluation`` (from :mod:`groundtruth`) adds the truth checks,
    ``cal`` (the Calibration) the opening table of fit quality."""
    m, f, cm = fit.model, fit.model.fit, fit.model.command
    facts = [("method", f.get("method")), ("iterations", f.get("iterations")), ("seconds", f.get("seconds")),
             ("converged", f.get("converged")), ("steps", log.steps), ("observations", len(log.obs_t)),
             ("sightings set aside", f.get("outliers_set_aside")),
             ("speed map v(c)", ", ".join(f"{x:.4g}" for x in cm.v_coef) + f" (powers of c/{cm.scale[0]:.3g})"),
             ("turn map w(c)", ", ".join(f"{x:.4g}" for x in cm.w_coef) + f" (powers of c/{cm.scale[1]:.3g})"),
             ("reading sigma", m.noise_text("reading")), ("bearing sigma (rad)", m.noise_text("bearing")),
             ("motion noise per step", ", ".join(f"{x:.4g}" for x in m.motion_noise)),
             ("sensor polynomial", m.curve_text())]
    ref, others = None, None
    if evaluation is not None:
        ref = evaluation["_vicon_model"]
        me, pr = evaluation["map_error"], evaluation["position_rms"]
        facts += [("turn map RMS vs truth fit", f"{me['w']['rms']:.4f} rad/s ({100 * me['w']['fraction']:.1f} % of range)"),
                  ("speed map RMS vs truth fit", f"{me['v']['rms']:.4f} m/s ({100 * me['v']['fraction']:.1f} % of range)")]
        facts += [(f"position RMS: {k.replace('_', ' ')}", f"{v:.3f} m") for k, v in pr.items()]
        others = {"identity-model graph": evaluation["_trajectories"]["identity_graph"]}
    info = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in facts)
    body = ["<h1>casm-graph calibration (continuous commands)</h1>", fit_quality(cal) if cal is not None else "",
            f"<h2>The fit</h2><table>{info}</table>", *effect_panels(fit),
            "<h2>Command maps</h2>", png(maps_figure(log, fit, ref)),
            "<h2>Sensor model</h2>", png(sensor_figure(log, fit, None)),
            "<h2>Trajectory</h2>", png(trajectory_figure(log, fit.poses, fit.pose_std, others)),
            *(["<h2>Motion noise by region (regional_motion_noise)</h2>", png(regional_noise_figure(log, fit))]
              if "regional_motion_noise" in m.effects else []),
            "<h2>Residuals</h2>", png(residual_figure(log, fit)),
            "<h2>Cost per iteration</h2>", png(cost_figure(fit))]
    path.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>casm-graph calibration</title>"
                    f"<style>{STYLE}</style></head><body>{''.join(body)}</body></html>")
