"""Residual correlation as system-identification tools show it (MATLAB's ``resid``): the autocorrelation of
the sightings' residuals, and the cross-correlation of each motion axis's residual with the changes of the
model's own velocity on that axis, both with a 99 % band for white residuals.

A missing effect that acts through time leaves its trace here rather than against any one covariate: an
actuator lag makes the forward residual follow each change of the forward velocity over the next fraction
of a second, with the opposite sign (a one-sided dip at positive lags), though its mean against any
covariate is flat (speeding up and slowing down cancel). The motion residuals are smoothing residuals,
autocorrelated by construction, so only their cross-correlation is shown; the sightings' residuals are
white when the model is right.
"""
from __future__ import annotations

import numpy as np

from casm_graph.fit.residuals import Channel

Z99 = 2.576                  # two-sided 99 % quantile of the standard normal
LAGS = 25
MOTION = ("forward", "lateral", "turn")


def _standard(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, float) - np.mean(x)
    s = np.std(x)
    return x / s if s > 0 else x * 0.0


def acf(r: np.ndarray, lags: int = LAGS) -> np.ndarray:
    """Autocorrelation of the series ``r`` at lags 1..``lags`` (fewer when the series is short)."""
    z = _standard(r)
    n = len(z)
    return np.array([np.sum(z[k:] * z[:-k]) / n for k in range(1, min(lags, n - 1) + 1)])


def ccf(r: np.ndarray, u: np.ndarray, lags: int = LAGS) -> tuple[np.ndarray, np.ndarray]:
    """(lags, correlation of r[k] with u[k - lag]) for lag in -lags..lags: positive lags mean the input came first."""
    zr, zu = _standard(r), _standard(u)
    n = len(zr)
    ks = np.arange(-min(lags, n - 1), min(lags, n - 1) + 1)
    out = np.array([np.sum(zr[k:] * zu[:n - k]) / n if k >= 0 else np.sum(zr[:n + k] * zu[-k:]) / n for k in ks])
    return ks, out


def correlation(chs: dict[str, Channel], lags: int = LAGS) -> dict:
    """Per channel: the sightings' autocorrelation, or a motion axis's cross-correlation with the change of its
    commanded velocity (``Channel.command``).

    Series are in time order; the lag unit is the channel's median time step (``step_s``). ``band`` is the
    99 % half-width for white residuals, ``outside`` how many lags leave it (about 1 % do by chance).
    """
    out = {}
    for name, ch in chs.items():
        order = np.argsort(ch.time, kind="stable")
        r = np.asarray(ch.residual, float)[order]
        if len(r) < 3 * lags:
            continue
        band = Z99 / np.sqrt(len(r))
        step = float(np.median(np.diff(ch.time[order])))
        rec = {"step_s": step, "band": float(band)}
        if name in MOTION:
            if ch.command is None:
                continue
            u = np.asarray(ch.command, float)[order]
            du = np.diff(u, prepend=u[:1])
            if not np.all(np.isfinite(du)) or np.ptp(du) == 0:
                continue
            ks, c = ccf(r, du, lags)
            i = int(np.argmax(np.abs(c)))
            rec.update(series="cross", lags=ks.tolist(), values=c.tolist(), outside=int(np.sum(np.abs(c) > band)),
                       peak=float(c[i]), peak_lag_s=float(ks[i] * step))
        else:
            a = acf(r, lags)
            i = int(np.argmax(np.abs(a)))
            rec.update(series="auto", lags=list(range(1, len(a) + 1)), values=a.tolist(),
                       outside=int(np.sum(np.abs(a) > band)), peak=float(a[i]), peak_lag_s=float((i + 1) * step))
        out[name] = rec
    return out


def strongest(corr: dict) -> tuple[str, float]:
    """(channel, peak |correlation| over its band): where the time structure is strongest."""
    best = ("", 0.0)
    for ch, rec in corr.items():
        ratio = abs(rec["peak"]) / rec["band"]
        if ratio > best[1]:
            best = (ch, float(ratio))
    return best
