"""The numbers behind the diagnosis report's trace views: per-landmark means, the sightings' tails, and the share
of its modelled motion the robot achieved over time (a fade's trace: spread over every step, it hardly shows in
binned residuals, for the smoothed path takes most of it in; the diagnosis tests its trend too)."""
from __future__ import annotations

import numpy as np
from scipy.stats import norm


def landmark_means(diag, channel: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(landmarks, mean residual, its standard error) of ``channel``'s sightings per landmark."""
    d = diag.residuals[channel]
    lm = d.covariates["landmark"]
    ids = np.unique(lm)
    m = np.array([d.residual[lm == i].mean() for i in ids])
    se = np.array([d.residual[lm == i].std() / np.sqrt(max((lm == i).sum(), 1)) for i in ids])
    return ids, m, se


def normal_tail(beyond: float = 4.0) -> float:
    """The share of a standard normal more than ``beyond`` sigmas out (either side)."""
    return float(2 * norm.sf(beyond))


def tail_share(r: np.ndarray, beyond: float = 4.0) -> float:
    """The share of whitened residuals ``r`` more than ``beyond`` sigmas out."""
    r = np.asarray(r, float)
    r = r[np.isfinite(r)]
    return float(np.mean(np.abs(r) > beyond)) if len(r) else 0.0


def speed_share(channel, edges: np.ndarray, block: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The share of its modelled motion a motion ``channel`` achieved within each time bin (``edges``, s), and its
    standard error: least squares of the residual displacement on the modelled one, over blocks of ``block`` s (the
    smoothed residuals drift together over seconds)."""
    e, m, t = blocked(channel, block)
    k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(edges) - 2)
    share, se = np.full(len(edges) - 1, np.nan), np.full(len(edges) - 1, np.nan)
    for b in range(len(edges) - 1):
        sel = k == b
        mm = float(np.sum(m[sel] ** 2))
        if sel.sum() >= 3 and mm > 0:
            g = float(np.sum(e[sel] * m[sel])) / mm
            share[b] = 1 + g
            se[b] = np.sqrt(np.sum((e[sel] - g * m[sel]) ** 2 * m[sel] ** 2)) / mm
    return share, se


def blocked(channel, block: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(residual displacement, modelled displacement, mid time) of a motion ``channel`` summed over ``block`` s."""
    order = np.argsort(channel.time)
    t = channel.time[order]
    e, m = channel.raw[order], (channel.command * channel.span)[order]
    ok = np.isfinite(e) & np.isfinite(m)
    t, e, m = t[ok], e[ok], m[ok]
    k = np.floor((t - t[0]) / block).astype(int) if len(t) else np.zeros(0, int)
    n = k[-1] + 1 if len(k) else 0
    count = np.bincount(k, minlength=n)
    keep = count > 0
    return (np.bincount(k, e, n)[keep], np.bincount(k, m, n)[keep],
            (np.bincount(k, t, n)[keep] / count[keep]))


def speed_trend(channel, block: float = 2.0, memory: float = 10.0) -> tuple[float, float]:
    """(change of the achieved share of the modelled motion per minute, its t): least squares of the residual
    displacement on the modelled one times time, over blocks of ``block`` s, with Newey and West's standard error
    over ``memory`` s of neighbouring blocks (slip that persists for seconds correlates them)."""
    e, m, t = blocked(channel, block)
    if len(e) < 4:
        return 0.0, 0.0
    x = np.column_stack([m, m * (t - t.mean()) / 60])
    coef, *_ = np.linalg.lstsq(x, e, rcond=None)
    bread = np.linalg.pinv(x.T @ x)
    u = x * (e - x @ coef)[:, None]
    meat = u.T @ u
    lags = int(round(memory / block))
    for k in range(1, min(lags, len(u) - 1) + 1):
        g = u[k:].T @ u[:-k]
        meat += (1 - k / (lags + 1)) * (g + g.T)
    se = float(np.sqrt(max((bread @ meat @ bread)[1, 1], 0.0)))
    return float(coef[1]), float(coef[1] / se) if se > 0 else 0.0


def moving(diag) -> list[str]:
    """The motion channels whose model moves the robot: those a scale of its speed can show on."""
    return moving_channels(diag.residuals)


def moving_channels(chs: dict) -> list[str]:
    """The motion channels of ``chs`` (name -> residual channel) whose model moves the robot: the turn, and each
    axis whose mean modelled speed is at least a tenth of the fastest translation's."""
    size = {ch: float(np.mean(np.abs(d.command))) for ch in ("forward", "lateral", "turn")
            if (d := chs.get(ch)) is not None and d.command is not None and d.span is not None
            and np.any(np.abs(d.command) > 0)}
    big = max((v for ch, v in size.items() if ch != "turn"), default=0.0)
    return [ch for ch, v in size.items() if ch == "turn" or v > 0.1 * big]
