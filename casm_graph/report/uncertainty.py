"""UNC/report.html: what the log tells how well, what it cannot pin down, and what data to collect next.

An action-table model gets its velocity table's std per action; a continuous-command model its
command maps with their 90 % bands over the commands the log drove, and the commands it rarely
drove. The sensor curve's band appears where the log measures readings.
"""
from __future__ import annotations

import html
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import corner
import numpy as np
from matplotlib.figure import Figure

from casm_graph.models.command_model import AXIS_WORDS, CommandModel, map_name
from casm_graph.models.velocity_table import VelocityTable
from casm_graph.report.pages import STYLE, png, subplots
from casm_graph.sim.aibo import true_reading

WEAK_FACTOR = 2.5         # an action whose std exceeds this many times the typical one is weakly observed
PINNED_WIDTH = 0.5        # a noise level is pinned down when its 90 % interval spans less than +-50 %
MIN_READINGS = 5          # a 0.1 m distance bin with fewer readings counts as not seen
COMMAND_BINS = 10         # bins over each command's range ...
RARE_FRACTION = 0.01      # ... one holding less than this share of the steps counts as rarely driven
UNITS = {"reading_sigma": "reading units", "bearing_sigma": "rad", "motion_noise_forward": "m/step",
         "motion_noise_lateral": "m/step", "motion_noise_turn": "rad/step"}


def true_values(unc) -> dict:
    """Simulator truth of each sampled quantity, when the log came with truth_model.json."""
    t = unc.truth
    if t is None:
        return {}
    sm, mn = t.get("sensor_model", {}), t.get("motion_noise")
    out = {"reading_sigma": sm.get("reading_sigma", sm.get("range_sigma")), "bearing_sigma": sm.get("bearing_sigma")}
    if mn is not None:
        out.update(motion_noise_forward=mn[0], motion_noise_lateral=mn[1], motion_noise_turn=mn[2])
    for name in unc.intervals:
        if "." in name:
            eff, par = name.split(".", 1)
            v = t.get("effects", {}).get(eff, {}).get(par)
            out[name] = v if v is not None else (0.0 if eff not in t.get("effects", {}) else None)
    return {k: float(v) for k, v in out.items() if v is not None and k in unc.intervals}


def true_table(unc) -> np.ndarray | None:
    t = unc.truth
    if t is None or unc.model.action.kind != VelocityTable.kind:
        return None
    tab = t.get("action_model", {}).get("velocities", {})
    ids = [str(int(a)) for a in unc.model.action_ids]
    return np.array([tab[a] for a in ids]) if all(a in tab for a in ids) else None


# ------------------------------------------------------------------------------- assessment
def action_usage(unc) -> tuple[np.ndarray, np.ndarray]:
    """(runs, seconds) of every action of the model in the log."""
    log, ids = unc.log, unc.model.action_ids
    act = np.searchsorted(ids, log.action)
    starts = np.concatenate([[True], act[1:] != act[:-1]])
    runs = np.bincount(act[starts], minlength=len(ids))
    secs = np.bincount(act, weights=log.dt, minlength=len(ids))
    return runs, secs


def seen_distances(unc) -> np.ndarray:
    """Distance of every reading from the MAP trajectory."""
    return unc.ml.reading_distances()


def visited_distances(unc) -> tuple[float, float]:
    """Smallest and largest distance the robot ever stood from a landmark (seen or not)."""
    p = unc.ml.state.poses[:, :2]
    d = np.hypot(p[:, None, 0] - unc.log.landmark_xy[None, :, 0], p[:, None, 1] - unc.log.landmark_xy[None, :, 1])
    return float(d.min()), float(d.max())


def unseen_ranges(unc, step: float = 0.1) -> list[tuple[float, float]]:
    """Distance intervals the robot stood at but saw (almost) no landmark from."""
    d = seen_distances(unc)
    lo, hi = visited_distances(unc)
    edges = np.arange(np.floor(lo / step) * step, hi + step, step)
    n, _ = np.histogram(d, edges)
    out = []
    for a, b, k in zip(edges[:-1], edges[1:], n):
        if k < MIN_READINGS:
            if out and abs(out[-1][1] - a) < 1e-9:
                out[-1] = (out[-1][0], float(b))
            else:
                out.append((float(a), float(b)))
    return out


def command_band(unc, which: int, points: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(commands, mapped velocity, its Laplace std) of the command model's map ``which`` (``CommandModel.maps``:
    speed, [sideways,] turn) over the log's commands."""
    cm = unc.model.command
    _, col, axis, part = cm.maps[which]
    c = unc.log.controls[:, col]
    grid = np.linspace(c.min(), c.max(), points)
    controls = np.zeros((points, unc.log.controls.shape[1]))
    controls[:, col] = grid
    basis = cm.basis(controls)[axis]
    C = unc.cov_theta[part, part]
    return grid, basis @ cm.params[part], np.sqrt(np.clip(np.einsum("ni,ij,nj->n", basis, C, basis), 0, None))


def rare_commands(unc, which: int) -> list[tuple[float, float]]:
    """Command intervals (``COMMAND_BINS`` over the log's range) driven in fewer than ``RARE_FRACTION`` of the steps,
    for map ``which``."""
    c = unc.log.controls[:, unc.model.command.maps[which][1]]
    n, edges = np.histogram(c, COMMAND_BINS)
    out = []
    for a, b, k in zip(edges[:-1], edges[1:], n):
        if k < RARE_FRACTION * len(c):
            if out and abs(out[-1][1] - a) < 1e-12:
                out[-1] = (out[-1][0], float(b))
            else:
                out.append((float(a), float(b)))
    return out


def _assess_table(unc, known, weak, advice) -> dict:
    """The velocity table's typical std, and the weakly observed actions with the running time that would fix them."""
    m = unc.model
    runs, secs = action_usage(unc)
    std = m.velocity_std
    typical = np.median(std, axis=0)
    ratio = np.max(std / typical, axis=1)
    weak_act = np.flatnonzero((ratio > WEAK_FACTOR) | (runs <= 1))
    known.append(f"velocity table: typical 90 % half-width vx {1645 * typical[0]:.1f} mm/s, "
                 f"vy {1645 * typical[1]:.1f} mm/s, w {1.645 * typical[2]:.3f} rad/s "
                 f"(median over {len(m.action_ids)} actions, {np.median(secs):.0f} s of data each)")
    for i in weak_act:
        a = int(m.action_ids[i])
        weak.append(f"action {a}: {runs[i]} run(s), {secs[i]:.1f} s; std vx {1000 * std[i, 0]:.1f} mm/s, "
                    f"vy {1000 * std[i, 1]:.1f} mm/s, w {std[i, 2]:.3f} rad/s ({ratio[i]:.1f} x typical)")
        need = secs[i] * (ratio[i] ** 2 - 1)
        advice.append(f"run action {a} for about {max(need, 5.0):.0f} s more (in runs of a few seconds) to bring "
                      f"its std to the typical level")
    return {"weak_actions": weak_act.tolist(), "runs": runs, "seconds": secs}


def _assess_command(unc, known, weak, advice) -> dict:
    """Each command map's 90 % band over the commands driven, and the commands the log rarely drove."""
    rare = {}
    for which, (cmd, _, axis, _) in enumerate(unc.model.command.maps):
        name, unit = map_name(axis), AXIS_WORDS[axis][1]
        grid, _, s = command_band(unc, which)
        known.append(f"{name}: 90 % half-width {1.645 * np.median(s):.3g} {unit} (median) to "
                     f"{1.645 * np.max(s):.3g} {unit} (widest) over the commands {cmd} = {grid[0]:.3g} to "
                     f"{grid[-1]:.3g} the log drove")
        rare[cmd] = rare_commands(unc, which)
        for a, b in rare[cmd]:
            weak.append(f"{name} at {cmd} = {a:.3g} to {b:.3g}: driven in under {100 * RARE_FRACTION:.0f} % of the "
                        f"steps, so the map there leans on its polynomial form")
            advice.append(f"drive {cmd} = {a:.3g} to {b:.3g} for a while (a few per cent of the log) if the robot "
                          f"will be commanded there")
    return {"rare_commands": rare}


def assess(unc) -> dict:
    """Known-how-well, cannot-pin-down and advice, as sentences and flags (the report prints them)."""
    known, weak, advice = [], [], []
    flags = {}
    for n, s in unc.intervals.items():
        lo, hi = s["ci90"]
        med = s["median"]
        pr = unc.priors[n]
        plo, phi = pr.bounds()
        rel = (hi - lo) / (2 * abs(med)) if med else np.inf
        at_prior = ((pr.kind == "loguniform" and lo < 3 * plo)
                    or (pr.kind == "uniform" and lo <= plo + 0.02 * (phi - plo)))
        unit = UNITS.get(n, "")
        if rel < PINNED_WIDTH and not at_prior:
            known.append(f"{n} = {med:.4g} {unit} (90 % interval {lo:.4g} to {hi:.4g}, +-{100 * rel:.0f} %)")
            flags[n] = "pinned"
        else:
            weak.append(f"{n}: the log bounds it only loosely ({lo:.4g} to {hi:.4g} {unit}); "
                        f"below about {hi:.3g} it cannot tell the values apart, so the interval's lower end "
                        f"follows the prior ({pr.describe()})")
            flags[n] = "weak"
            if n.startswith("motion_noise"):
                what = SECTIONS[unc.model.action.kind].noun
                advice.append(f"{n}: a longer log (the interval narrows roughly as 1/sqrt(length)) or a more "
                              f"precise sensor; until then the {what}' std below already includes the "
                              f"spread this level leaves")
            else:
                advice.append(f"{n}: more observations of this channel")
    m = unc.model
    out = SECTIONS[m.action.kind].assess(unc, known, weak, advice)
    gaps, vis = [], (np.nan, np.nan)
    if m.has("reading") and len(seen_distances(unc)):
        band_std = m.reading_std(np.linspace(*m.distance_range, 50))
        known.append(f"sensor curve: 90 % band +-{1.645 * np.median(band_std):.3g} (median) to "
                     f"+-{1.645 * np.max(band_std):.3g} (widest) over the distances seen, "
                     f"{m.distance_range[0]:.2f} to {m.distance_range[1]:.2f} m")
        gaps = unseen_ranges(unc)
        vis = visited_distances(unc)
    for a, b in gaps:
        mid = 0.5 * (a + b)
        s = float(m.reading_std(mid))
        weak.append(f"distances {a:.1f} to {b:.1f} m: the robot stood there but saw no landmark from there, so the "
                    f"sensor curve is extrapolated (std {s:.3g} at {mid:.2f} m)")
        lo_seen, hi_seen = m.distance_range
        where = "closer than" if b <= lo_seen + 1e-9 else ("farther than" if a >= hi_seen - 1e-9 else "between")
        advice.append(f"sightings at {a:.1f} to {b:.1f} m ({where} any seen), if the sensor can detect "
                      f"landmarks there; otherwise do not use the curve outside {m.distance_range[0]:.2f} to "
                      f"{m.distance_range[1]:.2f} m")
    return {"known": known, "weak": weak, "advice": advice, "flags": flags, "gaps": gaps, "visited": vis, **out}


# ---------------------------------------------------------------------------------- figures
def corner_figure(unc):
    ch = unc.chain
    truths = true_values(unc)
    scale = ["log" if n in UNITS else "linear" for n in ch.names]     # sigmas on log axes
    side = 2.0 * len(ch.names) + 1.0         # corner's own size rule; given a figure it makes no pyplot one
    fig = corner.corner(ch.samples, fig=Figure(figsize=(side, side)), labels=ch.names, quantiles=[0.05, 0.5, 0.95], show_titles=True, axes_scale=scale,
                        title_fmt=".3g", truths=[truths.get(n) for n in ch.names] if truths else None,
                        truth_color="C3", label_kwargs={"fontsize": 8}, title_kwargs={"fontsize": 8},
                        quiet=True)      # a short chain's flat contours: the chain's own warning says it is short
    return fig


def trace_figure(unc):
    ch = unc.chain
    d = len(ch.names)
    fig, axes = subplots(d, 1, figsize=(9, 1.6 * d + 0.5), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        ax.plot(ch.chain[:, :, i], lw=0.4, alpha=0.5, color="k")
        if ch.names[i] in UNITS:
            ax.set_yscale("log")
        ax.axvline(ch.burn_in, color="C3", lw=1)
        ax.set_ylabel(ch.names[i], fontsize=7)
        ax.set_title(f"tau {ch.tau[i]:.1f} steps", fontsize=7, loc="right")
    axes[-1, 0].set_xlabel(f"step (red: end of burn-in at {ch.burn_in})")
    fig.tight_layout()
    return fig


def sensor_band_figure(unc, verdict):
    m = unc.model
    lo, hi = verdict["visited"]
    d = np.linspace(max(lo, 0.05), hi, 300)
    mean, s = m.reading(d), m.reading_std(d)
    fig, (ax, axh) = subplots(2, 1, figsize=(8, 5.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.fill_between(d, mean - 1.645 * s, mean + 1.645 * s, color="C0", alpha=0.3, label="90 % band")
    ax.plot(d, mean, "C0", lw=1.5, label="learned curve")
    t = unc.truth
    sm = t.get("sensor_model", {}) if t is not None else {}
    if "camera" in sm:
        ax.plot(d, true_reading(t, d), "C3--", lw=1.2, label="true")
    elif "reading_poly" in sm:
        ax.plot(d, np.polynomial.polynomial.polyval(d, sm["reading_poly"]), "C3--", lw=1.2, label="true")
    for a, b in verdict["gaps"]:
        ax.axvspan(a, b, color="0.85", zorder=0)
        axh.axvspan(a, b, color="0.85", zorder=0)
    ds = seen_distances(unc)
    r = m.reading(ds)
    ax.set_ylim(np.min(r) - 0.2 * np.ptp(r), np.max(r) + 0.2 * np.ptp(r))
    ax.set(ylabel="reading", title="Sensor curve and its 90 % band (grey: distances stood at but never seen)")
    ax.legend(fontsize=8)
    axh.hist(ds, bins=np.arange(0, hi + 0.1, 0.1), color="0.4")
    axh.set(xlabel="distance (m)", ylabel="readings")
    fig.tight_layout()
    return fig


def velocity_std_figure(unc, verdict):
    m = unc.model
    std = m.velocity_std
    fig, axes = subplots(3, 1, figsize=(10, 6), sharex=True)
    x = np.arange(len(m.action_ids))
    weak = np.zeros(len(x), bool)
    weak[verdict["weak_actions"]] = True
    for k, (ax, lab, f) in enumerate(zip(axes, ["vx std (mm/s)", "vy std (mm/s)", "w std (rad/s)"], [1000, 1000, 1])):
        ax.bar(x, f * std[:, k], color=np.where(weak, "C3", "C0"))
        ax.axhline(f * WEAK_FACTOR * np.median(std[:, k]), color="k", lw=0.6, ls="--")
        ax.set_ylabel(lab, fontsize=8)
    ax2 = axes[0].twinx()
    ax2.plot(x, verdict["seconds"], "k.", ms=4)
    ax2.set_ylabel("seconds run (dots)", fontsize=8)
    axes[-1].set_xticks(x, [str(int(a)) for a in m.action_ids], fontsize=6)
    axes[-1].set_xlabel("action (red: weakly observed; dashed: weak threshold)")
    fig.tight_layout()
    return fig


def command_map_figure(unc, verdict):
    """Speed and turn maps with their 90 % bands over the commands driven, the commands' histogram below."""
    maps = unc.model.command.maps
    fig, axes = subplots(2, len(maps), figsize=(5 * len(maps), 5.5), sharex="col", gridspec_kw={"height_ratios": [3, 1]})
    for which, (cmd, col, axis, _) in enumerate(maps):
        what, unit = AXIS_WORDS[axis]
        ax, axh = axes[0, which], axes[1, which]
        grid, mean, s = command_band(unc, which)
        ax.fill_between(grid, mean - 1.645 * s, mean + 1.645 * s, color="C0", alpha=0.3, label="90 % band")
        ax.plot(grid, mean, "C0", lw=1.5, label="learned map")
        ax.plot(grid, grid, "k:", lw=0.8, label="velocity = command")
        for a, b in verdict["rare_commands"][cmd]:
            ax.axvspan(a, b, color="0.85", zorder=0)
            axh.axvspan(a, b, color="0.85", zorder=0)
        ax.set(ylabel=f"actual {what} ({unit})", title=f"{what.split()[0].capitalize()} map (grey: rarely driven)")
        ax.legend(fontsize=8)
        axh.hist(unc.log.controls[:, col], bins=40, color="0.4")
        axh.set(xlabel=f"command {cmd} ({unit})", ylabel="steps")
    fig.tight_layout()
    return fig


def _command_table(unc) -> str:
    cm = unc.model.command
    rows = []
    for cmd, col, _, _ in cm.maps:
        coef, std = cm.coefficients(cmd)
        scale = cm.scale[col]
        for i, (c, sd) in enumerate(zip(coef, std)):
            rows.append(f"<tr><td>{cmd}</td><td>({cmd} / {scale:.3g})^{i}</td>"
                        f"<td>{c:+.4f} &plusmn; {1.645 * sd:.4f}</td></tr>")
        term = cm.cross_coefficient(cmd)
        if term is not None:
            rows.append(f"<tr><td>{cmd}</td><td>v / {cm.scale[0]:.3g}</td>"
                        f"<td>{term[0]:+.4f} &plusmn; {1.645 * term[1]:.4f}</td></tr>")
    return ("<table><tr><th>map</th><th>term</th><th>coefficient &plusmn; 90 %</th></tr>" + "".join(rows)
            + "</table>")


# ----------------------------------------------------------------------------------- report
def _table(unc) -> str:
    truths = true_values(unc)
    head = "<tr><th>quantity</th><th>model</th><th>median</th><th>90 % interval</th><th>tau</th><th>prior</th>"
    head += "<th>truth</th><th>inside</th></tr>" if truths else "</tr>"
    rows = []
    for i, (n, s) in enumerate(unc.intervals.items()):
        cells = [n, f"{unc.ml.x_map[i]:.4g}", f"{s['median']:.4g}", f"{s['ci90'][0]:.4g} to {s['ci90'][1]:.4g}",
                 f"{unc.chain.tau[i]:.1f}", html.escape(unc.priors[n].describe())]
        if truths:
            t = truths.get(n)
            cells += ["" if t is None else f"{t:.4g}",
                      "" if t is None else ("yes" if s["ci90"][0] <= t <= s["ci90"][1] else "<b class='bad'>no</b>")]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return f"<table>{head}{''.join(rows)}</table>"


def _velocity_table(unc, verdict) -> str:
    m = unc.model
    tv = true_table(unc)
    head = "<tr><th>action</th><th>runs</th><th>s</th><th>vx (m/s)</th><th>vy (m/s)</th><th>w (rad/s)</th>"
    head += "<th>truth inside 90 %</th></tr>" if tv is not None else "</tr>"
    rows = []
    for i, a in enumerate(m.action_ids):
        cells = [str(int(a)), str(verdict["runs"][i]), f"{verdict['seconds'][i]:.0f}"]
        cells += [f"{v:+.3f} &plusmn; {1.645 * s:.3f}" for v, s in zip(m.velocities[i], m.velocity_std[i])]
        if tv is not None:
            z = np.abs(m.velocities[i] - tv[i]) / m.velocity_std[i]
            cells.append(" ".join("yes" if q <= 1.645 else "<b class='bad'>no</b>" for q in z))
        cls = " class='bad'" if i in verdict["weak_actions"] else ""
        rows.append(f"<tr{cls}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    cover = ""
    if tv is not None:
        z = np.abs(m.velocities - tv) / m.velocity_std
        cover = (f"<p>Against the simulator's table, {100 * np.mean(z <= 1.645):.0f} % of the "
                 f"{z.size} 90 % intervals contain the true velocity.</p>")
    return cover + f"<table>{head}{''.join(rows)}</table>"


@dataclass(frozen=True)
class ActionSection:
    """What the page says of one kind of action model: its name, what the log pins down of it, how it is shown."""

    noun: str
    assess: Callable      # (unc, known, weak, advice) -> the verdict's part on the action model
    show: Callable        # (unc, verdict) -> its figure and table, HTML


SECTIONS = {VelocityTable.kind: ActionSection("velocity table", _assess_table,
                                              lambda unc, v: png(velocity_std_figure(unc, v)) + _velocity_table(unc, v)),
            CommandModel.kind: ActionSection("command maps", _assess_command,
                                             lambda unc, v: png(command_map_figure(unc, v)) + _command_table(unc))}


def write(out: Path, unc) -> None:
    """report.html, corner.png and trace.png in ``out``."""
    out = Path(out)
    verdict = assess(unc)
    cf = corner_figure(unc)
    cf.savefig(out / "corner.png", dpi=90, bbox_inches="tight")
    tf = trace_figure(unc)
    tf.savefig(out / "trace.png", dpi=90, bbox_inches="tight")
    ch = unc.chain
    e = html.escape
    lst = lambda items: "<ul>" + "".join(f"<li>{e(x)}</li>" for x in items) + "</ul>"   # noqa: E731
    warn = "".join(f"<p class='bad'>{e(n)}</p>" for n in ch.notes)
    sensor = (f"<h2>Sensor curve</h2>{png(sensor_band_figure(unc, verdict))}"
              if np.isfinite(verdict["visited"][0]) else "")      # only where the log measures readings
    section = SECTIONS[unc.model.action.kind]
    action = (f"<h2>{section.noun.capitalize()} (Laplace marginals averaged over the noise posterior)</h2>"
              f"{section.show(unc, verdict)}")
    integrated = ", ".join(unc.ml.integrated_out)
    body = f"""<!doctype html><html><head><meta charset="utf-8"><title>casm-graph uncertainty</title>
<style>{STYLE}</style></head><body>
<h1>How well does this log pin the model down?</h1>{warn}
<h2>Known, and how well</h2>{lst(verdict['known'])}
<h2>What the log cannot pin down</h2>{lst(verdict['weak']) if verdict['weak'] else '<p>Nothing stands out.</p>'}
<h2>What to collect next</h2>{lst(verdict['advice']) if verdict['advice'] else '<p>Nothing urgent.</p>'}
<h2>Noise levels (emcee)</h2>
<p>Sampled under their marginal likelihood with these integrated out: {e(integrated)} (Laplace
approximation at the MAP, re-factored for every sample: {1000 * ch.seconds_per_evaluation:.1f} ms per
evaluation, {1000 * ch.cpu_seconds_per_evaluation:.1f} ms of CPU, on {unc.log.steps} steps;
{ch.evaluations} evaluations).
{ch.walkers} walkers, {ch.steps} steps, burn-in {ch.burn_in}, thinned by {ch.thin}:
{len(ch.samples)} samples; acceptance {ch.acceptance:.2f}.</p>
{_table(unc)}
<h3>Corner plot</h3>{png(cf)}
<h3>Traces</h3>{png(tf)}
{sensor}
{action}
<p style="color:#777">{unc.seconds:.1f} s</p></body></html>"""
    (out / "report.html").write_text(body)
