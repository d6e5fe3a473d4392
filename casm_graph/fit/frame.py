"""The map frame a fit's poses are reported in when an effect's parameters leave it free.

A moved landmark's offsets are fitted as the map's shape (moving, turning or scaling every landmark together is
not seen), which spreads one landmark's move over all of them and shifts the path with them; the effect then
chooses the rigid motion that keeps the unmoved landmarks on the map (:meth:`Effect.reframe`) and the poses follow
it; where no effect holds a length, the scale too, which the action model and the sensor curve follow
(:meth:`Model.scaled`). The likelihood does not change.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from casm_graph.fit.result import Fit
from casm_graph.io.log import Log, wrap
from casm_graph.models.effects.landmark_offset import similar


def moved(poses: np.ndarray, std: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``poses`` (n, 3) and their std after the similarity ``g`` = (phi, tx, ty[, s]) of the map."""
    k = g[3] if len(g) > 3 else 1.0
    c, s = np.cos(g[0]), np.sin(g[0])
    out = np.array(poses, float)
    out[:, :2] = similar(g, out[:, :2])
    out[:, 2] = poses[:, 2] + g[0]
    if np.all(np.abs(poses[:, 2]) <= np.pi):             # headings given wrapped stay wrapped
        out[:, 2] = wrap(out[:, 2])
    sd = np.array(std, float)
    sd[:, 0] = k * np.sqrt((c * std[:, 0]) ** 2 + (s * std[:, 1]) ** 2)   # the x, y correlation is not kept
    sd[:, 1] = k * np.sqrt((s * std[:, 0]) ** 2 + (c * std[:, 1]) ** 2)
    return out, sd


def in_map_frame(log: Log, fit: Fit, classes) -> Fit:
    """``fit`` with each effect of ``classes`` that leaves the map's frame free choosing it, and the poses moved with
    it; as it is when another effect is bound to the map's frame (a field over the floor). The map's scale is chosen
    too when every effect is ``scale_free``: the action model and the sensor curve then follow it."""
    if any(c.map_bound for c in classes):
        return fit
    scale = all(c.scale_free for c in classes)
    for cls in classes:
        entry = fit.model.effects.get(cls.name)
        if entry is None:
            continue
        effect = cls(log)
        theta = effect.theta_of(entry)
        g = effect.reframe(theta, scale)
        if g is None:
            continue
        poses, std = moved(fit.poses, fit.pose_std, g)
        model = fit.model if len(g) < 4 or g[3] == 1 else fit.model.scaled(g[3])
        model = replace(model, effects={**model.effects, cls.name: effect.describe(theta)})
        fit = replace(fit, model=model, poses=poses, pose_std=std)
    return fit
