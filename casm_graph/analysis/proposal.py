"""Discovery beyond the catalog: a sparse regression of the motion residuals on a library of terms.

When no catalog effect explains the structure, each motion axis's residual velocity (measured minus
modelled, over each residual's span) is regressed on the library of
:func:`casm_graph.models.effects.proposal.library` (heading, position, time, speed, turn rate, alone
and times the axis's own velocity, the turn rate over the speed, and the oscillation in time whose period fits best). Residuals are averaged over blocks of about a second first: the
smoothed trajectory's per-step residuals are correlated over a few steps.
scikit-learn's LARS lasso with BIC picks the terms; a least-squares refit on them gives coefficients
and t-values (a Newey-West covariance: block means of a smoothed trajectory still drift slowly
together), and terms under ``min_t`` are dropped. The result is a readable equation the user can
add as an effect (``--effect proposal``) and watch the error fall.
"""
from __future__ import annotations

import warnings

from dataclasses import asdict, dataclass

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import LassoLarsIC

from casm_graph.models.effects.proposal import (AXES, PERIODIC, equation, features, library, periodic_terms,
                                                split_term, with_own)

COVARIATE = {"cos(heading)": "heading", "sin(heading)": "heading", "x": "x", "y": "y", "t": "time",
             "speed": "speed", "v_forward": "speed", "v_lateral": "speed", "w": "turn_rate", "|w|": "turn_rate",
             "1/speed": "speed"}


@dataclass(frozen=True)
class ProposalOptions:
    """How the regression searches; recorded in diagnosis.json with its result."""

    block_s: float = 1.0          # s of residuals averaged into one regression row
    min_t: float = 5.0            # least |t| of a kept term: high, for the library's many tries
    last_test_t: float = 6.0      # a ``none`` verdict turns ``unexplained`` on the proposal alone only when its
    #                               strongest term reaches this |t| (the independent world's heading effects: 11.4
    #                               and 21.8; an omni world's lag, once added, left a v_lateral*sin(heading) at 5.3)
    hac_s: float = 20.0           # s of lags the Newey-West covariance spans (smoothed residuals drift slowly)
    min_r2: float = 0.02          # least share of the block-mean variance the proposal must explain
    shortest_period: float = 30.0  # s: the fastest oscillation in time the library tries
    min_cycles: float = 1.5       # the slowest: this many periods must fit in the log
    periods: int = 40             # periods tried, evenly on a log scale
    needs_form: bool = True       # an unexplained motion structure for which no term passes is the slip's slow
    #                               wander: the verdict is none (car world, the lag added: lateral residuals against
    #                               time, p 1e-15, no term; the uncataloged effects each had theirs)


def _blocks(time: np.ndarray, block_s: float) -> np.ndarray:
    """Block index of each row: consecutive ``block_s`` seconds."""
    return np.floor((time - time[0]) / block_s).astype(int)


def _block_means(y: np.ndarray, X: np.ndarray, w: np.ndarray, b: np.ndarray):
    """Span-weighted means of ``y`` and ``X`` per block."""
    n = b.max() + 1
    W = np.bincount(b, w, n)
    keep = W > 0
    ym = np.bincount(b, w * y, n)[keep] / W[keep]
    Xm = np.column_stack([np.bincount(b, w * X[:, j], n)[keep] / W[keep] for j in range(X.shape[1])])
    return ym, Xm


def _steps(chs: dict, axis: str):
    """Context (pose, time) and model velocity (n, 3) of each motion residual, as the effect hook sees them."""
    cov = chs[axis].covariates
    ctx = {"pose": np.column_stack([cov["x"], cov["y"], cov["heading"]]), "t": np.asarray(cov["time"], float)}
    v = np.column_stack([np.asarray(chs[a].command, float) for a in AXES])
    return ctx, v


def _best_period(y: np.ndarray, ctx: dict, v: np.ndarray, axis: str, b: np.ndarray, w: np.ndarray,
                 options: ProposalOptions) -> float | None:
    """The period (s) of the oscillation in time that best fits the block means, or None on a short log."""
    t = ctx["t"]
    longest = (t.max() - t.min()) / options.min_cycles
    if longest < options.shortest_period:
        return None
    best, best_p = np.inf, None
    for period in np.geomspace(options.shortest_period, longest, options.periods):
        ym, Xm = _block_means(y, features(axis, with_own(axis, periodic_terms(period)), ctx, v), w, b)
        A = np.column_stack([np.ones(len(ym)), Xm])
        rss = np.sum((ym - A @ np.linalg.lstsq(A, ym, rcond=None)[0]) ** 2)
        if rss < best:
            best, best_p = rss, float(round(period))
    return best_p


def ols_hac(y: np.ndarray, X: np.ndarray, lags: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of ``y`` on ``X``: coefficients, t-values with the Newey-West (Bartlett) covariance over
    ``lags`` rows and the small-sample factor n / (n - k), and residuals. Written out (ten lines, as
    statsmodels' ``OLS.fit(cov_type="HAC", use_correction=True)`` computes it, to 1e-14) rather than pulling
    statsmodels and pandas in for one formula."""
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    e = y - X @ coef
    u = X * e[:, None]
    S = u.T @ u
    for lag in range(1, min(lags, len(y) - 1) + 1):
        G = u[lag:].T @ u[:-lag]
        S += (1.0 - lag / (lags + 1.0)) * (G + G.T)
    bread = np.linalg.pinv(X.T @ X)
    cov = bread @ S @ bread * len(y) / max(len(y) - X.shape[1], 1)
    return coef, coef / np.sqrt(np.maximum(np.diag(cov), 1e-300)), e


def distinct(X: np.ndarray, use: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """``use`` without the columns that repeat an earlier used one (correlation 1 within ``tol``): on a robot that
    never reverses, speed is v_forward, and least squares would split one term's coefficient between the two."""
    use = use.copy()
    cols = np.flatnonzero(use)
    if len(cols) < 2:
        return use
    R = np.corrcoef(X[:, cols], rowvar=False)
    for j in range(1, len(cols)):
        if np.any(np.abs(R[j, :j][use[cols[:j]]]) > 1.0 - tol):
            use[cols[j]] = False
    return use


def fit_axis(chs: dict, axis: str, options: ProposalOptions) -> dict | None:
    """The sparse regression on one motion axis: kept terms, coefficients, t-values, R^2; None if nothing."""
    ch = chs.get(axis)
    if ch is None or ch.span is None or ch.command is None or any(chs.get(a) is None for a in AXES):
        return None
    span = np.asarray(ch.span, float)
    ctx, v = _steps(chs, axis)
    y = ch.raw / np.where(span > 0, span, np.nan)             # residual velocity on the axis
    ok = np.isfinite(y) & np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(ctx["pose"]), axis=1)
    y, v, w = y[ok], v[ok], span[ok]
    ctx = {k: c[ok] for k, c in ctx.items()}
    if len(y) < 50:
        return None
    b = _blocks(ctx["t"], options.block_s)
    period = _best_period(y, ctx, v, axis, b, w, options)
    names = library(axis, () if period is None else (period,))
    ym, Xm = _block_means(y, features(axis, names, ctx, v), w, b)
    if len(ym) < 3 * len(names):
        return None
    mu, sd = Xm.mean(axis=0), Xm.std(axis=0)
    use = distinct(Xm, sd > 1e-12 * (1 + np.abs(mu)))
    yc = ym - ym.mean()
    with warnings.catch_warnings():      # collinear terms (sin and cos of a short log's heading): LARS drops one
        warnings.simplefilter("ignore", ConvergenceWarning)
        lasso = LassoLarsIC(criterion="bic", fit_intercept=False).fit((Xm[:, use] - mu[use]) / sd[use], yc)
    cols = np.flatnonzero(use)[np.abs(lasso.coef_) > 0]
    while len(cols):                     # least squares on the lasso's terms; the weakest goes until all pass
        coef, tval, res = ols_hac(ym, np.column_stack([np.ones(len(ym)), Xm[:, cols]]),
                                  max(1, int(round(options.hac_s / options.block_s))))
        coef, tval = coef[1:], tval[1:]
        weakest = int(np.argmin(np.abs(tval)))
        if abs(tval[weakest]) >= options.min_t:
            break
        cols = np.delete(cols, weakest)
    if not len(cols):
        return None
    r2 = 1.0 - float(res @ res) / float(yc @ yc)
    if r2 < options.min_r2:
        return None
    key = [f"{axis}: {names[c]}" for c in cols]
    return {"axis": axis, "terms": dict(zip(key, map(float, coef))), "t_values": dict(zip(key, map(float, tval))),
            "r2": r2, "blocks": int(len(ym)), "period_tried_s": period}


def propose(chs: dict, options: ProposalOptions | None = None) -> dict:
    """The proposal over every motion axis: terms (``"<axis>: <term>"`` -> coefficient), equation lines, and
    each axis's fit; empty when no axis has a term that passes."""
    o = options or ProposalOptions()
    fits = [f for f in (fit_axis(chs, a, o) for a in AXES) if f is not None]
    if not fits:
        return {}
    terms = {k: v for f in fits for k, v in f["terms"].items()}
    return {"terms": terms, "equation": equation(terms),
            "axes": {f["axis"]: {k: f[k] for k in ("r2", "blocks", "t_values", "period_tried_s")} for f in fits},
            "options": asdict(o)}


def strongest_t(proposal: dict) -> float | None:
    """The largest |t| of the proposal's terms (None without terms)."""
    return max((abs(v) for f in proposal.get("axes", {}).values() for v in f["t_values"].values()), default=None)


def term_covariates(proposal: dict) -> list[tuple[str, str]]:
    """(axis, diagnosis covariate) of every term of the proposal, strongest (largest |t|) first: the covariate is
    heading, x, y, time, speed or turn_rate."""
    out = []
    for axis, term in sorted(((a, k) for a, f in proposal["axes"].items() for k in f["t_values"]),
                             key=lambda ak: -abs(proposal["axes"][ak[0]]["t_values"][ak[1]])):
        base = split_term(axis, term.split(": ", 1)[1])[1]
        out.append((axis, "time" if PERIODIC.match(base) else COVARIATE.get(base, base)))
    return out


def covariate(proposal: dict) -> str:
    """The diagnosis covariate of the proposal's strongest term."""
    return term_covariates(proposal)[0][1]


def words(proposal: dict) -> str:
    """The proposal in a sentence for the summary, with how to add it."""
    if not proposal:
        return ""
    r2 = ", ".join(f"{a} {100 * v['r2']:.0f} %" for a, v in proposal["axes"].items())
    return ("Proposed from the motion residuals (sparse regression over a library of terms; share of the "
            f"residual variance it explains: {r2}): " + "; ".join(proposal["equation"])
            + ". Add it with `--effect proposal --proposal DIAG/diagnosis.json`.")
