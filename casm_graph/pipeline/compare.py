"""``casm-graph compare``: a learned model against tables measured independently (stopwatch, tape measure).

DIR/sensor.csv (``distance,reading[,std]``) and DIR/actions.csv (``action,vx,vy,w``), either or
both. Differences per action and along the sensor curve, with the model's own standard deviations
where it has them (z-scores say whether a difference is within the learned uncertainty).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from casm_graph.io.log import MAX_POSITION, MAX_READING, MAX_SPEED, LogError, _Table
from casm_graph.io.output import atomic_dir, checked_out, json_text
from casm_graph.models.model import Model
from casm_graph.report import pages as report


def read_measured(directory: Path) -> tuple[dict | None, dict | None]:
    d = Path(directory)
    if not d.is_dir():
        raise LogError(f"{d}: not a directory")
    sensor = actions = None
    if (d / "sensor.csv").is_file():
        t = _Table(d / "sensor.csv")
        t.require("distance", "reading")
        t.nonempty()
        sensor = {"distance": t.numbers("distance", bound=MAX_POSITION, unit=" m"),
                  "reading": t.numbers("reading", bound=MAX_READING),
                  "std": t.numbers("std", allow_empty=True, bound=MAX_READING) if t.has("std") else None}
        for col in ("distance", "std"):
            bad = np.flatnonzero(sensor[col] < 0) if sensor[col] is not None else []
            if len(bad):
                raise LogError(f"sensor.csv, row {bad[0] + 1}, column '{col}': {sensor[col][bad[0]]:g} is negative")
    if (d / "actions.csv").is_file():
        t = _Table(d / "actions.csv")
        t.require("action", "vx", "vy", "w")
        t.nonempty()
        actions = {"action": t.integers("action"),
                   "v": np.column_stack([t.numbers(c, bound=MAX_SPEED, unit=" m/s or rad/s")
                                         for c in ("vx", "vy", "w")])}
    if sensor is None and actions is None:
        raise LogError(f"{d}: neither sensor.csv nor actions.csv is there")
    return sensor, actions


def compare(model: Model, sensor: dict | None, actions: dict | None) -> dict:
    out: dict = {"summary": []}
    if actions is not None:
        known = np.isin(actions["action"], model.action_ids)
        if not known.any():
            raise LogError("actions.csv: none of its actions is in the model")
        ids = actions["action"][known]
        meas = actions["v"][known]
        learned = model.velocity_of(ids)
        diff = learned - meas
        std = model.velocity_std[model.action.rows_of(ids)] if model.velocity_std is not None else None
        rms = np.sqrt(np.mean(diff ** 2, axis=0))
        out["actions"] = {"rms_difference": {"vx": rms[0], "vy": rms[1], "w": rms[2]},
                          "per_action": [{"action": int(a), "measured": m.tolist(), "learned": l.tolist(),
                                          "difference": d.tolist(),
                                          "z": (d / s).tolist() if std is not None else None}
                                         for a, m, l, d, s in zip(ids, meas, learned, diff,
                                                                  std if std is not None else [None] * len(ids))],
                          "not_in_model": actions["action"][~known].tolist()}
        out["summary"].append(f"actions: RMS difference vx {1000 * rms[0]:.1f} mm/s, vy {1000 * rms[1]:.1f} mm/s, "
                              f"w {rms[2]:.4f} rad/s over {len(ids)} actions")
        if std is not None:
            z = diff / std
            out["actions"]["within_2_std"] = float(np.mean(np.abs(z) < 2))
            out["summary"].append(f"  {100 * np.mean(np.abs(z) < 2):.0f} % of differences within 2 learned std")
    if sensor is not None:
        pred = model.reading(sensor["distance"])
        diff = pred - sensor["reading"]
        lo, hi = model.distance_range
        inside = (sensor["distance"] >= lo) & (sensor["distance"] <= hi) if hi > lo else np.ones(len(diff), bool)
        out["sensor"] = {"rms_difference": float(np.sqrt(np.mean(diff ** 2))),
                         "rms_difference_inside_range": float(np.sqrt(np.mean(diff[inside] ** 2))) if inside.any() else None,
                         "points": [{"distance": float(d), "measured": float(m), "learned": float(p)}
                                    for d, m, p in zip(sensor["distance"], sensor["reading"], pred)]}
        out["summary"].append(f"sensor: RMS difference {out['sensor']['rms_difference']:.2f} over {len(diff)} distances"
                              + (f" ({out['sensor']['rms_difference_inside_range']:.2f} inside the learned range "
                                 f"{lo:.2f}-{hi:.2f} m)" if inside.any() and not inside.all() else ""))
    return out


def figure(model: Model, sensor, actions):
    n = (sensor is not None) + (actions is not None)
    fig, axes = report.subplots(1, n, figsize=(6.5 * n, 4), squeeze=False)
    k = 0
    if sensor is not None:
        ax = axes[0, k]
        k += 1
        lo, hi = model.distance_range
        d = np.linspace(min(sensor["distance"].min(), lo or sensor["distance"].min()),
                        max(sensor["distance"].max(), hi or sensor["distance"].max()), 200)
        ax.plot(d, model.reading(d), "C0", lw=2, label="learned")
        if hi > lo:
            ax.axvspan(lo, hi, color="C0", alpha=0.07, label="distances in the log")
        std = sensor["std"]
        ax.errorbar(sensor["distance"], sensor["reading"], None if std is None else std, fmt="C3o", label="measured")
        ax.set(xlabel="distance (m)", ylabel="reading", title="sensor curve")
        ax.legend()
    if actions is not None:
        ax = axes[0, k]
        known = np.isin(actions["action"], model.action_ids)
        meas = actions["v"][known]
        learned = model.velocity_of(actions["action"][known])
        for c, (name, unit) in enumerate((("vx", 1), ("vy", 1), ("w", 1))):
            ax.plot(meas[:, c], learned[:, c], "o", ms=4, label=name)
        lim = [min(meas.min(), learned.min()), max(meas.max(), learned.max())]
        ax.plot(lim, lim, "k", lw=0.5)
        ax.set(xlabel="measured (m/s, rad/s)", ylabel="learned", title="action table")
        ax.legend()
    fig.tight_layout()
    return fig


def run(model_path, measured_dir, out, force: bool = False) -> dict:
    """Compare the model at ``model_path`` with the tables in ``measured_dir``; write OUT all or nothing."""
    checked_out(out, force, inputs=[model_path, measured_dir])
    model = Model.load(model_path)
    sensor, actions = read_measured(Path(measured_dir))
    res = compare(model, sensor, actions)
    img = report.png(figure(model, sensor, actions))
    lines = "".join(f"<p>{s}</p>" for s in res["summary"])
    with atomic_dir(out, force=force, inputs=[model_path, measured_dir]) as tmp:
        (tmp / "comparison.json").write_text(json_text(res))
        (tmp / "report.html").write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>casm-graph compare"
                                         f"</title><style>{report.STYLE}</style></head><body><h1>Learned vs measured</h1>"
                                         f"{lines}{img}</body></html>")
    return res
