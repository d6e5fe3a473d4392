"""Predictive residuals, as system-identification tools compare a model with measured output: from each
smoothed pose the model runs open-loop for a horizon (0.5-5 s), and the sightings it predicts there are
compared with the measured ones.

The smoothed residuals of a fit are small almost by construction (the trajectory bends to the data); a
model that lacks an effect of the motion (a lag, friction, fade) predicts worse the further it runs on its
own, so the error per horizon, before and after adding an effect, shows what the effect bought. Errors
are in each channel's own unit (a model's noise levels change when an effect is added; the unit does
not), as a robust scale (1.4826 x the median absolute residual), so a few wild sightings do not set it.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

import factors.command

HORIZONS = (0.0, 0.5, 1.0, 2.0, 5.0)      # s; 0 is the smoothed residual itself


def open_loop(poses: np.ndarray, velocity: np.ndarray, dt: np.ndarray, n: int, lead: float = 0.0) -> np.ndarray:
    """(T+1, 3) poses: pose k predicted from the smoothed pose ``n`` steps earlier (from pose 0 for the first
    ``n``), integrating the model's body ``velocity`` (T, 3) over the steps between, each step along its heading
    ``lead`` of its turn on (:func:`factors.command.turned`)."""
    poses = np.asarray(poses, float)
    inc = factors.command.turned(np.asarray(velocity, float) * np.asarray(dt, float)[:, None], lead)
    big = np.concatenate([[0.0], np.cumsum(inc[:, 2])])            # the model's own heading from an origin
    path = np.concatenate([[0j], np.cumsum(np.exp(1j * big[:-1]) * (inc[:, 0] + 1j * inc[:, 1]))])
    k = np.arange(len(poses))
    s = np.maximum(k - int(n), 0)
    turn = poses[s, 2] - big[s]
    z = poses[s, 0] + 1j * poses[s, 1] + np.exp(1j * turn) * (path[k] - path[s])
    heading = np.angle(np.exp(1j * (turn + big[k])))
    return np.column_stack([z.real, z.imag, heading])


def robust_scale(r: np.ndarray) -> float:
    """1.4826 x the median absolute value of the finite entries (NaN when there are none)."""
    r = np.asarray(r, float)
    r = r[np.isfinite(r)]
    return float(1.4826 * np.median(np.abs(r))) if len(r) else float("nan")


def predictive(poses: np.ndarray, velocity: np.ndarray, dt: np.ndarray,
               residuals: Callable[[np.ndarray], dict], horizons=HORIZONS, lead: float = 0.0) -> dict:
    """Error of the sightings predicted open-loop over each horizon, per channel.

    ``poses`` (T+1, 3) are the smoothed poses at every step, ``velocity`` (T, 3) the model's body velocity
    of each step, ``residuals(trajectory)`` the measured-minus-predicted sightings of a (T+1, 3)
    trajectory per channel (NaN where a sighting is not measured or set aside). Horizons longer than a
    tenth of the log are left out.
    """
    step = float(np.median(dt))
    span = float(np.sum(dt))
    hs = [float(h) for h in horizons if h <= 0.1 * span]
    out = {"horizons_s": hs, "channels": {}}
    for h in hs:
        for ch, r in residuals(open_loop(poses, velocity, dt, int(round(h / step)), lead)).items():
            if np.isfinite(r).any():
                out["channels"].setdefault(ch, []).append(robust_scale(r))
    return out


def words(pred: dict, horizon: float = 2.0) -> str:
    """One sentence: how far the predictions drift over ``horizon`` (or the longest one there is)."""
    hs = pred.get("horizons_s", [])
    if len(hs) < 2 or not pred.get("channels"):
        return ""
    i = min(range(len(hs)), key=lambda j: abs(hs[j] - horizon))
    parts = [f"{ch} {v[0]:.3g} smoothed, {v[i]:.3g} predicted {hs[i]:g} s ahead"
             for ch, v in pred["channels"].items()]
    return "Run open-loop from the smoothed poses, the model predicts the sightings with errors (robust scale, " \
           "the channel's unit): " + "; ".join(parts) + "."
