"""Where a model fails and which physical effect is missing (``casm-graph diagnose``).

1. The model is refitted on the log as it stands (same procedure as every candidate, so the
   comparison is fair) and its residual channels are tested: whiteness (Ljung-Box) and, for each
   covariate, the dependence of the residuals' mean and of their spread on it (binned means,
   one-way ANOVA F-test; Brown-Forsythe on absolute deviations for the spread). The residuals of
   a time series are autocorrelated, so the F statistic is deflated by the variance inflation of
   an AR(1) fit and the denominator degrees of freedom use the effective sample size. Strength is
   omega squared: the share of residual variance the covariate explains, bias-corrected.
2. Each applicable catalog effect not already in the model is added and fitted (warm start) and
   scored by delta BIC (Laplace log-likelihood, trajectory integrated out) and by the held-out
   negative log-likelihood on time-blocked folds: the effect's parameters and the noise levels are
   fitted with one third of the observations hidden, and the hidden ones are scored by
   log p(O_all) - log p(O_train) with those held fixed and the table, polynomial and poses fitted
   in both (:func:`casm_graph.analysis.candidates.table.heldout_log_likelihood`; a command map's candidates
   are settled on its coarse graph instead, :mod:`casm_graph.analysis.candidates`). The folds run for the candidates whose
   delta BIC is below zero; one that does not even improve the in-sample fit cannot be the verdict,
   and its ``heldout_nll_drop`` is null.
3. The verdict names the candidate that BIC supports strongly and that either improves the
   held-out score or was built for the strongest residual structure; ``none`` when no candidate is
   supported and no channel shows material structure; ``unexplained:<covariate>`` when structure
   remains that no candidate accounts for (a motion dependence on place only when it holds across the robot's
   visits).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy import stats

from casm_graph.analysis.predictive import predictive
from casm_graph.analysis.predictive import words as predictive_words
from casm_graph.analysis.proposal import ProposalOptions, propose
from casm_graph.analysis.proposal import strongest_t, term_covariates
from casm_graph.analysis.proposal import words as proposal_words
from casm_graph.analysis.trace_measures import moving_channels, speed_trend
from casm_graph.fit.residuals import CATEGORICAL, Channel, ljung_box
from casm_graph.graph.actions.command_poly import COMMAND_CHANGE
from casm_graph.io.log import Log, LogError, wrap
from casm_graph.io.output import atomic_dir, json_text
from casm_graph.models.effects import REGISTRY
from casm_graph.models.effects.proposal import proposal_effect

SCHEMA = "casm-graph/diagnosis/1"


@dataclass(frozen=True)
class DiagnoseOptions:
    """How a diagnosis tests the residuals and weighs the candidates; recorded in diagnosis.json ``options``.

    The evidence thresholds were calibrated on effect-free simulated logs (BENCHMARKS.md).
    """

    bins: int = 10                     # quantile bins of a numeric covariate
    min_per_bin: int = 20              # fewer residuals than this make no bin (or category)
    structure_p: float = 1e-6          # residual structure counts when this significant ...
    structure_omega2: float = 0.01     # ... and it explains at least this share of the residual variance
    structure_share: float = 0.5       # a candidate is built for the structure when it explains one at least this
                                       # share as strong as the strongest (an effect shows in several channels)
    own_structure: bool = True         # a candidate without held-out folds (continuous logs) is also built for a
    #                                    structure of its own pairs at p below structure_p times the tests run over
    #                                    its pairs tested: the search over every pair and the test of a candidate's
    #                                    few pairs then share one family-wise error (omni worlds: a 0.16-s latency's
    #                                    turn residuals against the turn acceleration, p 7e-6, and a 0.011-per-minute
    #                                    fade's time trend were none)
    refit_candidates: int = 2          # with no candidate supported, the first this many lowering BIC strongly are
    #                                    refitted on the base's graph (continuous logs), and one whose fit leaves the
    #                                    structure the unexplained verdict would name no longer material takes that as
    #                                    its second line: the effect seen through a covariate it is not built for (omni
    #                                    world, carpet seed 4: forward residuals against time, 5.1 %, p 3e-21; 0.2 %,
    #                                    p 0.18, with the patch; a continuous world's speed oscillating in time keeps
    #                                    3.4 % of 4.3 %, p 4e-37, with the friction grid; 0: never) ...
    refit_share: float = 0.25          # ... and at most this share of its strength left: the structure gone, not crossing a
    #                                    threshold (a car's turn residuals against the turn rate at 1.2 %, p 2e-11, left
    #                                    at 0.7 %, p 2e-6, by a friction field)
    bic_support: float = -10.0         # a verdict's delta BIC at most this (strong evidence on Kass and Raftery's scale)
    heldout_support: float = 0.0       # and the held-out log-likelihood must improve by more than this
    heldout_veto: float = 50.0         # a structure match does not support a candidate whose held-out score falls by more
    bic_tie: float = 2.0               # delta BICs closer than this are no evidence either way: the held-out score decides
    lookalike_bic: float = 6.0         # supported candidates within this of the best explain the data about equally
    lookalike_relative: float = 0.1    # continuous logs: also within this share of the best's delta BIC (a profile is a
    #                                    short re-optimisation whose settling error grows with the change it makes)
    lookalike_prediction: float = 0.5  # or when one's fit reproduces at least this share of the change the other's
    #                                    makes to the predicted sightings (squared, in sigmas) ...
    lookalike_gain: float = 0.5        # ... and the runner-up gains at least this share of the verdict's delta BIC
    screen_share: float = 0.25         # action tables: a candidate is fitted only when the score test predicts a gain
    #                                    (twice the log-likelihood) of at least this share of its BIC penalty (0: all)
    candidate_rounds: int = 2          # noise-step rounds fitting (settling) each candidate and the base. On action
    #                                    tables three let a latency whose poses must move from the base's reach its
    #                                    optimum (table seed 3: -2,158 against the lag's -2,053; with two -1,820
    #                                    against -1,912, its look-alike), but cost 1.16x the diagnosis (Aibo lag10:
    #                                    about 3.0x calibrate); on continuous logs a latency's velocity window follows
    #                                    its delay from one round to the next
    candidate_iterations: int = 8      # and LM iterations per round (continuous logs: also re-settling the model
    #                                    before its residuals)
    leader_rounds: int | None = None   # when two or more candidates lead (supported by BIC, each with at least
    #                                    ``lookalike_gain`` of the best's delta BIC), they and the base go on from their
    #                                    fits to this many rounds in all (continuous logs: at most, until the
    #                                    log-likelihood moves by less than a nat) before the verdict; 0 or at most
    #                                    candidate_rounds: never. None: the kind's own (LEADER_ROUNDS): 3 on action
    #                                    tables, where the independent world's latencies are then named 10 of 10 (8
    #                                    with two), at 1.06x the diagnosis on Aibo lag10; off on continuous logs, where
    #                                    40 names the independent world's strong latencies (seeds 7, 9, 10: the latency
    #                                    ahead by 138-1,100; with two the lag by 53-950), but a two-minute lag world
    #                                    then goes to the latency (-24,878 against -24,663), the lag's delay held at its
    #                                    two-round profile
    folds: int = 3                     # time-blocked held-out folds
    fold_iterations: int = 4           # LM iterations bounding each fold's fits
    fold_tol: float = 1e-5             # relative cost change that ends a fold fit (about 0.1 nat on these logs)
    heldout_gate: float = 0.0          # candidates with delta BIC below this get held-out folds
    command_change: float = COMMAND_CHANGE   # continuous logs: a command jump of this share of its range starts an "action"
    lag_order_support: float = -10.0   # continuous logs: a one-stage lag this supported is profiled with two too
    confirm_members: bool = True       # continuous logs: a leading family's members within ``lookalike_gain`` of its
    #                                    best are fitted as ``calibrate --effect`` fits them (the fine graph) and the
    #                                    member with the best BIC there is kept: the coarse graph's knots, a second
    #                                    apart, blur a patch's sharp edges (omni world seed 1: the 4 x 4 grid ahead of
    #                                    the patch by 3,288 nats on it; the patch ahead by 3,229 in the calibration,
    #                                    which then leaves none where the grid left battery_fade)
    proposal_challenge: float = 2.0    # a catalog verdict on the motion channel yields to the sparse regression's
    #                                    proposal, fitted as a candidate, when the proposal gains at least this many
    #                                    times its log-likelihood and lowers BIC by more than the look-alike margin
    #                                    below it (continuous world: a speed oscillating in time was named
    #                                    battery_fade, turn rate growing with speed battery_fade or surface_friction;
    #                                    0: never)
    feedback_lead: float = 1.0         # s: a motion residual that follows a commanded covariate's later values (up to
    #                                    this lead) more than its own is the controller correcting the noise, not
    #                                    structure of the model (0: no such test)
    visit_p: float = 0.01              # a motion channel's dependence on place (x, y or the floor's cells), as a
    #                                    candidate's own structure, a sparse-regression term or the structure an
    #                                    unexplained verdict names, counts only when the
    #                                    bins' means hold across the robot's visits (a strong structure when one of the
    #                                    candidate's own place pairs does): tested against the spread of the
    #                                    visits' means within each bin at this level (a floor slows the robot on every
    #                                    pass; noise that wanders for seconds differs from one pass to the next). Omni
    #                                    world, six minutes: the carpets' best place pair at 1e-13 to 0.003, an
    #                                    effect-free log's and the weakest fade's (named surface_friction without it)
    #                                    at 0.08 and 0.012 (0: no such test)
    visit_strong_p: float = 1e-4       # a candidate's own place pair holding across visits at this level, divided by
    #                                    the number of its own pairs tested across visits (one family-wise error),
    #                                    counts as its own structure however small a share of the variance it
    #                                    explains: a floor slows the robot a little on every pass (continuous world,
    #                                    carpet seed 5: forward residuals against y 0.59 %, across 169 visits p 7e-7,
    #                                    was none; an effect-free log's turn against x, 0.66 %, p 3e-5 over nine
    #                                    pairs, named surface_friction at 1e-4 per pair; 0: never)
    long_run_seconds: float = 0.0      # s: > 0 deflates a motion channel's test against each covariate by the long-run
    #                                    variance of its residuals' deviations from their groups' means (Bartlett's
    #                                    weights over lags up to this time), where it exceeds the lag-one (AR(1))
    #                                    inflation: slip that persists for seconds leaves smoothing residuals whose
    #                                    means drift more than a lag-one correlation says (0: the AR(1) inflation alone).
    #                                    Off: at 6 s on the omni world's six-minute logs a lag, once added, leaves none
    #                                    on 5 of 6 (3 without), but two carpets are named false_detections and
    #                                    battery_fade (surface_friction without)
    speed_trend: bool = True           # each moving motion channel is also tested for a trend over time of the share of
    #                                    its modelled motion achieved (``trend`` in its report; a pair (channel, time) of
    #                                    kind ``scale`` among a candidate's own pairs, never a material structure): a
    #                                    fade spread over every step hides from binned means, which the smoothed path
    #                                    takes in (continuous world, four minutes, seeds 6-17: fades named 8 of 12, 7
    #                                    without, at t -4.7 to -13.4; effect-free |t| <= 3.3, other effects' <= 3.7)
    trend_block: float = 2.0           # s: the trend test sums the residual and modelled motion over blocks this long
    trend_memory: float = 10.0         # s: and its standard error counts the correlation of blocks this far apart
    #                                    (effect-free seed 9: t -3.1 without, -3.3 with)
    proposal: ProposalOptions = field(default_factory=ProposalOptions)   # the equation search of an unexplained verdict

    def to_json(self) -> dict:
        return asdict(self)

    def leaders_settle(self, kind: str) -> int:
        """The leaders' rounds in all on a log of action model ``kind``: ``leader_rounds``, or the kind's own."""
        return self.leader_rounds if self.leader_rounds is not None else LEADER_ROUNDS.get(kind, 0)


LEADER_ROUNDS = {"table": 3, "command_poly": 0}     # each kind's leaders' rounds when the options leave them open
DEFAULTS = DiagnoseOptions()
BIC_SUPPORT = DEFAULTS.bic_support     # the default evidence a verdict needs, for scripts that count supported candidates


# --------------------------------------------------------------------------- statistics
def _inflation(r_time_ordered: np.ndarray) -> float:
    """Variance inflation (1 + rho) / (1 - rho) of means of an AR(1) series with lag-one correlation rho >= 0."""
    r = r_time_ordered - r_time_ordered.mean()
    rho = float(np.sum(r[1:] * r[:-1]) / max(np.sum(r * r), 1e-300))
    rho = min(max(rho, 0.0), 0.95)
    return (1 + rho) / (1 - rho)


def long_run_inflation(r: np.ndarray, g: np.ndarray, lags: int) -> float:
    """Long-run variance over variance of residuals ``r`` (time order) less their groups' (``g``, -1: none) means:
    1 + 2 sum over lags k up to ``lags`` of (1 - k / (lags + 1)) rho_k (Bartlett's weights, as Newey and West).
    Within-group deviations keep the structure under test out of the correlation that discounts it."""
    keep = g >= 0
    e = np.zeros(len(r))
    _, inv = np.unique(g[keep], return_inverse=True)
    means = np.bincount(inv, weights=r[keep]) / np.bincount(inv)
    e[keep] = r[keep] - means[inv]
    v = float(np.sum(e * e))
    if v <= 0 or lags < 1:
        return 1.0
    rho = [float(np.sum(e[k:] * e[:-k])) / v for k in range(1, min(lags, len(e) - 1) + 1)]
    return max(1.0, 1.0 + 2.0 * sum((1.0 - (k + 1) / (lags + 1)) * c for k, c in enumerate(rho)))


PLACE_COVARIATES = ("x", "y", "place")   # where the robot is: a motion residual's dependence on it repeats per visit
MIN_VISIT = 5                             # residuals a visit to a bin needs to count (shorter runs cross its edge)


def visits_anova(r: np.ndarray, g: np.ndarray) -> tuple[float, int]:
    """(p, visits) of the groups' means of residuals ``r`` (time order) tested against the spread of the means of
    their visits (runs of consecutive residuals in one group ``g``, -1: none, of at least ``MIN_VISIT``) within each
    group: a split-plot ANOVA whose error term is the visit, the unit a place effect repeats over. p is NaN (not
    tested) when fewer than two groups have visits or no group has two."""
    keep = g >= 0
    r, g = r[keep], g[keep]
    if len(r) == 0:
        return float("nan"), 0
    start = np.r_[True, g[1:] != g[:-1]]
    visit = np.cumsum(start) - 1
    n, total, label = np.bincount(visit), np.bincount(visit, weights=r), g[start]
    big = n >= MIN_VISIT
    n, total, label = n[big], total[big], label[big]
    groups, inv = np.unique(label, return_inverse=True)
    k, v = len(groups), len(n)
    if k < 2 or v <= k:
        return float("nan"), int(v)
    gn = np.bincount(inv, weights=n)
    gm = np.bincount(inv, weights=total) / gn
    between = float(np.sum(gn * (gm - total.sum() / n.sum()) ** 2)) / (k - 1)
    within = float(np.sum(n * (total / n - gm[inv]) ** 2)) / (v - k)
    return float(stats.f.sf(between / max(within, 1e-300), k - 1, v - k)), int(v)


def _groups(x: np.ndarray, categorical: bool, options: DiagnoseOptions = DEFAULTS) -> np.ndarray:
    """Group label of each row: categories with enough rows, or quantile bins of a numeric covariate."""
    if categorical:
        vals, inv, counts = np.unique(x, return_inverse=True, return_counts=True)
        big = counts >= options.min_per_bin
        return np.where(big[inv], inv, -1)
    bins = min(options.bins, max(len(x) // options.min_per_bin, 1))
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))


def anova(y: np.ndarray, g: np.ndarray, inflation: float) -> tuple[float, float]:
    """(omega squared, p) of one-way ANOVA of ``y`` on groups ``g`` with autocorrelation-deflated F."""
    keep = g >= 0
    y, g = y[keep], g[keep]
    labels, inv = np.unique(g, return_inverse=True)
    k, n = len(labels), len(y)
    if k < 2 or n <= k + 1:
        return 0.0, 1.0
    means = np.bincount(inv, weights=y) / np.bincount(inv)
    ssb = float(np.sum(np.bincount(inv) * (means - y.mean()) ** 2))
    sst = float(np.sum((y - y.mean()) ** 2))
    ssw = sst - ssb
    msw = ssw / (n - k)
    omega2 = max(0.0, (ssb - (k - 1) * msw) / (sst + msw)) if sst > 0 else 0.0
    n_eff = max(n / inflation, k + 2.0)
    F = (ssb / (k - 1)) / max(msw, 1e-300) / inflation
    p = float(stats.f.sf(F, k - 1, n_eff - k))
    omega2_eff = max(0.0, (ssb / inflation - (k - 1) * msw) / (sst + msw)) if sst > 0 else 0.0
    return min(omega2, omega2_eff), p


MOTION_CHANNELS = ("forward", "lateral", "turn")
SET_ASIDE = "Set aside as not physical"       # how the words of a candidate set aside begin


def set_aside_words(words: list[str]) -> list[str]:
    """The sentences of ``words`` naming a candidate set aside as not physical: kept whatever the verdict becomes."""
    return [w for w in words if w.startswith(SET_ASIDE)]


MIN_SHARE = 0.05        # the least share of its noise a residual keeps (1 - leverage) when standardised


def standardised(r: np.ndarray, leverage: np.ndarray | None) -> np.ndarray:
    """Residuals ``r`` divided by the square root of the share of their noise they keep, 1 - ``leverage`` (NaN: 0),
    so that their spread is their noise's whatever pins the poses."""
    if leverage is None:
        return r
    return r / np.sqrt(np.clip(1.0 - np.nan_to_num(leverage), MIN_SHARE, 1.0))


COMMANDED = ("speed", "turn_rate", "acceleration", "turn_acceleration")   # motion covariates the commands set


def feedback_strength(r: np.ndarray, x: np.ndarray, t: np.ndarray, inflation: float,
                      options: DiagnoseOptions = DEFAULTS) -> tuple[float, float]:
    """(strongest omega squared, its lead in s) of residuals ``r`` against the values ``x`` took up to
    ``options.feedback_lead`` later (all three in time order). A model error shows in the motion of the
    command that caused it, or after it (a lag); a closed loop's commands answer the noise that went before
    them, so the dependence grows with the lead (system identification's feedback test on the residuals'
    cross-correlation with the inputs)."""
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if options.feedback_lead <= 0 or step <= 0:
        return 0.0, 0.0
    best = (0.0, 0.0)
    for j in range(1, max(1, int(round(options.feedback_lead / step))) + 1):
        ok = np.isfinite(x[j:]) & np.isfinite(r[:-j])
        if ok.sum() < 3 * options.min_per_bin:
            break
        s, _ = anova(r[:-j][ok], _groups(x[j:][ok], False, options), inflation)
        best = max(best, (s, j * step))
    return best


def covariate_tests(ch: Channel, options: DiagnoseOptions = DEFAULTS) -> list[dict]:
    """Mean (and for sensor channels spread) dependence of a channel's residuals on each covariate, strongest first.

    Motion residuals are smoothing residuals: their spread follows each step's leverage (how many
    sightings pin it) rather than physics, so motion channels are tested for their mean only. A sensor
    channel's spread is tested on its residuals standardised by their leverage (``ch.leverage``: r / sqrt(1 - h)),
    so that sightings which pin their pose do not fake a spread that follows distance. A motion channel's commanded
    covariate whose dependence is significant or strong enough to count (a candidate's own structure) is tested
    for the closed loop's feedback too.
    """
    order = np.argsort(ch.time, kind="stable")
    r = ch.residual
    motion = ch.name in MOTION_CHANNELS
    r_t, t_t = r[order], ch.time[order]                  # in time order: the series tests
    infl = _inflation(r_t)
    step = float(np.median(np.diff(t_t))) if len(t_t) > 1 else 0.0
    lags = int(round(options.long_run_seconds / step)) if motion and options.long_run_seconds > 0 and step > 0 else 0
    rs = standardised(r, ch.leverage)
    dev = np.abs(rs - np.median(rs))
    infl_dev = _inflation(dev[order])
    out = []
    for name, x in ch.covariates.items():
        ok = np.isfinite(x) & np.isfinite(r)
        if ok.sum() < 3 * options.min_per_bin or np.ptp(x[ok]) == 0:
            continue
        cat = name in CATEGORICAL
        g = _groups(x[ok], cat, options)
        if lags:
            g_all = np.full(len(r), -1)
            g_all[ok] = g
            c_infl = max(infl, long_run_inflation(r_t, g_all[order], lags))
        else:
            c_infl = infl
        s_mean, p_mean = anova(r[ok], g, c_infl)
        if motion:
            lead, when = feedback_strength(r_t, x[order], t_t, c_infl, options) if name in COMMANDED and (
                p_mean < options.structure_p or s_mean >= options.structure_omega2) else (0.0, 0.0)
            rec = ({"name": name, "strength": s_mean, "p": p_mean, "kind": "mean"} if lead <= s_mean else
                   {"name": name, "strength": s_mean, "p": p_mean, "kind": "feedback",
                    "lead": when, "lead_strength": lead})
            if name in PLACE_COVARIATES and options.visit_p > 0:
                g_all = np.full(len(r), -1)
                g_all[ok] = g
                p_visits, visits = visits_anova(r_t, g_all[order])
                if np.isfinite(p_visits):
                    rec["visits_p"], rec["visits"] = p_visits, visits
            out.append(rec)
            continue
        s_spread, p_spread = anova(dev[ok], g, infl_dev)
        if s_spread > s_mean:
            out.append({"name": name, "strength": s_spread, "p": p_spread, "kind": "spread"})
        else:
            out.append({"name": name, "strength": s_mean, "p": p_mean, "kind": "mean"})
    out.sort(key=lambda d: (-d["strength"], d["p"]))
    return out


def trend_test(ch: Channel, options: DiagnoseOptions = DEFAULTS) -> dict:
    """The trend over time of the share of its modelled motion a motion channel achieved
    (:func:`~casm_graph.analysis.trace_measures.speed_trend`): ``rate`` per minute, its ``t`` and two-sided ``p``,
    and ``strength``, the share of the residual variance the trend's term explains."""
    rate, t = speed_trend(ch, options.trend_block, options.trend_memory)
    tau = (ch.time - np.nanmean(ch.time)) / 60
    fit = rate * ch.command * ch.span * tau
    ok = np.isfinite(fit) & np.isfinite(ch.raw)
    var = float(np.var(ch.raw[ok])) if ok.any() else 0.0
    return {"name": "time", "kind": "scale", "rate": rate, "t": t, "p": float(2 * stats.norm.sf(abs(t))),
            "strength": float(np.var(fit[ok]) / var) if var > 0 else 0.0}


def channel_report(chs: dict[str, Channel], options: DiagnoseOptions = DEFAULTS) -> dict:
    """Per channel: residual RMS (whitened and raw), whiteness, the covariate tests (:func:`covariate_tests`) and,
    for a moving motion channel, its ``trend`` (:func:`trend_test`, with ``options.speed_trend``)."""
    rep = {}
    moving = set(moving_channels(chs)) if options.speed_trend else set()
    for name, ch in chs.items():
        order = np.argsort(ch.time, kind="stable")
        rep[name] = {"rms": float(np.sqrt(np.mean(ch.residual ** 2))) if len(ch.residual) else float("nan"),
                     "rms_raw": float(np.sqrt(np.mean(ch.raw ** 2))) if len(ch.raw) else float("nan"),
                     "whiteness_p": ljung_box(ch.residual[order]),
                     "covariates": covariate_tests(ch, options)}
        if name in moving:
            rep[name]["trend"] = trend_test(ch, options)
    return rep


def structures(rep: dict, options: DiagnoseOptions = DEFAULTS) -> list[dict]:
    """Material residual structure: (channel, covariate) pairs past both thresholds, strongest first."""
    found = []
    for ch, r in rep.items():
        for c in r["covariates"]:
            if c["p"] < options.structure_p and c["strength"] >= options.structure_omega2 and c["kind"] != "feedback":
                found.append({"channel": ch, **c})
    found.sort(key=lambda d: -d["strength"])
    return found


# --------------------------------------------------------------------------- candidates
@dataclass
class Candidate:
    effect: str
    channel: str
    delta_bic: float
    heldout_nll_drop: float
    explanation: str
    delta_log_likelihood: float
    parameters: dict = field(default_factory=dict)
    seconds: float = 0.0
    heldout_skipped: str = "no in-sample gain (delta BIC >= 0), held-out folds not run"
    order: int | None = None         # a family's member (Effect.orders): its complexity
    orders: dict = field(default_factory=dict)   # every member's delta BIC, by order (the kept one the lowest)
    confirmed: dict = field(default_factory=dict)   # members fitted as calibrate fits them: log-likelihood by order
    screened: bool = False           # not fitted: delta BIC and log-likelihood are the score test's prediction
    implausible: str = ""            # why its fitted parameters cannot happen (Effect.implausible): kept out of verdicts
    prediction: dict | None = field(default=None, repr=False)   # the fit's predicted sightings (look-alike test)
    change: float = float("nan")     # RMS change the fit makes to the base's predicted sightings, in sigmas
    takes_away: dict = field(default_factory=dict)   # the structure its refit leaves immaterial (:func:`taking_away`)

    def to_json(self) -> dict:
        return {"effect": self.effect, "channel": self.channel, "delta_bic": self.delta_bic,
                "heldout_nll_drop": self.heldout_nll_drop, "explanation": self.explanation,
                "delta_log_likelihood": self.delta_log_likelihood, "parameters": self.parameters,
                **({} if np.isfinite(self.heldout_nll_drop) else {"heldout_skipped": self.heldout_skipped}),
                **({"order": self.order, "orders": {str(k): v for k, v in self.orders.items()}}
                   if self.orders else {}), **({"screened": True} if self.screened else {}),
                **({"confirmed": {str(k): v for k, v in self.confirmed.items()}} if self.confirmed else {}),
                **({"implausible": self.implausible} if self.implausible else {}),
                **({"sighting_change": self.change} if np.isfinite(self.change) else {}),
                **({"takes_away": self.takes_away} if self.takes_away else {})}

    @property
    def spec(self) -> str:
        """The name ``calibrate --effect`` takes for this candidate (``name:order`` for a family member other than
        the default)."""
        root = REGISTRY.get(self.effect)
        default = self.order is None or (root is not None and root.order == self.order)
        return self.effect if default else f"{self.effect}:{self.order}"


def family_members(cls) -> list:
    """``cls``, or each member of its family (``Effect.orders``): the forms a diagnosis fits and compares by BIC."""
    return [cls.of_order(k) for k in cls.orders] if cls.orders else [cls]


def family_best(cands: list[Candidate], chosen: dict | None = None) -> list[int]:
    """Indices (in order) of the candidate kept per effect: the member with the lowest delta BIC among those that
    lower it with a fit that can happen (any, when none does), or the order ``chosen`` names for it (a member
    confirmed on the calibration's graph). Changes nothing."""
    best: dict[str, int] = {}
    chosen = chosen or {}

    def rank(c: Candidate) -> tuple:
        return bool(c.implausible) or not c.delta_bic < 0.0, c.delta_bic

    for i, c in enumerate(cands):
        if c.effect in chosen:
            if c.order == chosen[c.effect]:
                best[c.effect] = i
        elif c.effect not in best or rank(c) < rank(cands[best[c.effect]]):
            best[c.effect] = i
    return sorted(best.values())


def best_of_family(cands: list[Candidate], chosen: dict | None = None) -> list[int]:
    """:func:`family_best`, each kept member of a family recording every member's delta BIC in ``orders``."""
    keep = family_best(cands, chosen)
    for i in keep:
        c = cands[i]
        if c.order is not None:
            c.orders = {k.order: k.delta_bic for k in cands if k.effect == c.effect}
    return keep


def leading(cands: list[Candidate], options: DiagnoseOptions = DEFAULTS) -> list[Candidate]:
    """The candidates a verdict or a look-alike group could name: BIC supports each strongly (delta BIC at most
    ``options.bic_support``) and each gains at least ``options.lookalike_gain`` of the best's delta BIC. Those are
    what more rounds of settling are spent on."""
    cands = [c for c in cands if not c.implausible]
    if not cands:
        return []
    best = min(c.delta_bic for c in cands)
    return [c for c in cands if c.delta_bic <= options.bic_support and c.delta_bic <= options.lookalike_gain * best]


def family_words(cands: list[Candidate], verdict_effect: str) -> list[str]:
    """A sentence on the complexity the data chose when the verdict's effect is a family."""
    c = next((c for c in cands if c.effect == verdict_effect and c.orders), None)
    if c is None:
        return []
    tried = ", ".join(f"order {k}: {v:+.1f}" for k, v in sorted(c.orders.items()))
    if c.confirmed:
        fitted = ", ".join(f"order {k}: {v:,.1f}" for k, v in sorted(c.confirmed.items()))
        return [f"{c.effect} is a family of forms (delta BIC {tried}); fitted as calibrate fits them, the leading "
                f"members reach log-likelihoods {fitted}, and BIC there keeps order {c.order}. "
                f"Add it with `calibrate --effect {c.spec}`."]
    return [f"{c.effect} is a family of forms; BIC chose order {c.order} (delta BIC {tried}). "
            f"Add it with `calibrate --effect {c.spec}`."]


def folds(log: Log, k: int = DEFAULTS.folds) -> list[np.ndarray]:
    """Masks of the observations kept for training in each of ``k`` contiguous time blocks."""
    t = log.obs_t
    edges = np.quantile(t, np.linspace(0, 1, k + 1))
    block = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, k - 1)
    return [block != f for f in range(k)]


SCREENED = "not fitted: the score test predicts too small a gain, held-out folds not run"
NO_FOLDS = "held-out folds are not run for continuous-command logs"
DECIDED = "not needed: a supported candidate lower in BIC by more than the look-alike margin decides the verdict"


def predicted_sightings(problem, st) -> dict:
    """The measured readings and bearings a fit predicts, and the sigmas they are compared in."""
    p = problem.predictions(st)
    log = problem.log
    r, b = np.isfinite(log.obs_reading), np.isfinite(log.obs_bearing)
    return {"reading": p["reading"][r], "bearing": p["bearing"][b], "reading_sigma": problem.reading_sigma,
            "bearing_sigma": problem.bearing_sigma}


def prediction_change(base: dict, p: dict) -> np.ndarray:
    """The change a fit's predicted sightings ``p`` make to the base's, in the base's sigmas (readings, bearings)."""
    return np.concatenate([(p["reading"] - base["reading"]) / base["reading_sigma"],
                           wrap(p["bearing"] - base["bearing"]) / base["bearing_sigma"]])


def sighting_change(base: dict | None, p: dict | None) -> float:
    """RMS over the sightings of the change a fit makes to the base's predictions, in sigmas (NaN without both)."""
    if base is None or p is None:
        return float("nan")
    d = prediction_change(base, p)
    return float(np.sqrt(np.mean(d ** 2))) if len(d) else float("nan")


def reproduced_share(base: dict, a: dict, b: dict) -> float:
    """The share of the change ``a``'s fit makes to the base's predicted sightings that ``b``'s makes too: 1 minus
    the squared difference of the two changes over the square of ``a``'s (in sigmas; 1 when they predict alike)."""
    da, db = prediction_change(base, a), prediction_change(base, b)
    size = float(da @ da)
    return float(1.0 - (da - db) @ (da - db) / size) if size > 0 else 0.0


# --------------------------------------------------------------------------- verdict
def lookalikes(cands: list[Candidate], verdict_effect: str, separated_by: dict | None = None,
               relative: float = 0.0, options: DiagnoseOptions = DEFAULTS, base: dict | None = None) -> list[dict]:
    """The candidates that explain the data about as well as the verdict's effect: supported by BIC and within
    ``options.lookalike_bic`` of it (less than strong evidence between them on Kass and Raftery's scale), or within
    ``relative`` times its own delta BIC where the scores carry an error that grows with the gain, or whose fit
    changes the predicted sightings alike (one reproduces ``options.lookalike_prediction`` of the change the other
    makes to ``base``'s predictions) while gaining ``options.lookalike_gain`` of the verdict's delta BIC: the
    sightings do not tell them apart, and the margin left is how each form suits the rest of the model (an
    independent world's camera latency was named actuator_lag at -1,912 against -1,442, each reproducing 28 % and
    59 % of the other's change). One group (the verdict first) with each member's delta BIC, held-out gain and
    shares reproduced, and what data would tell them apart (``separated_by``: effect name -> the effect class's
    ``distinguished_by``), or none."""
    best = next((c for c in cands if c.effect == verdict_effect), None)
    if best is None:
        return []
    within = max(options.lookalike_bic, relative * abs(best.delta_bic))

    def share(c) -> float:
        """The larger share of one fit's change to the predicted sightings the other reproduces."""
        if base is None or best.prediction is None or c.prediction is None:
            return float("nan")
        return max(reproduced_share(base, best.prediction, c.prediction),
                   reproduced_share(base, c.prediction, best.prediction))

    shares = {id(c): share(c) for c in cands
              if c is not best and c.delta_bic <= options.bic_support and not c.implausible}
    group = [best] + [c for c in cands if id(c) in shares and (
        abs(c.delta_bic - best.delta_bic) < within
        or (shares[id(c)] >= options.lookalike_prediction and c.delta_bic <= options.lookalike_gain * best.delta_bic))]
    if len(group) < 2:
        return []
    sep = separated_by or {}
    close = [c for c in group[1:] if abs(c.delta_bic - best.delta_bic) < within]
    closer = ((f"closer than {options.lookalike_bic:g}" if within == options.lookalike_bic else
               f"closer than {100 * relative:g} % of the best, the error these scores carry") if close else
              f"one reproducing at least {100 * options.lookalike_prediction:g} % of the other's change to the "
              f"predicted sightings, with at least {100 * options.lookalike_gain:g} % of its gain")
    return [{"effects": [c.effect for c in group], "delta_bic": [c.delta_bic for c in group], "closer_than": closer,
             "heldout_nll_drop": [c.heldout_nll_drop for c in group],
             "prediction_share": [1.0] + [None if np.isnan(shares[id(c)]) else shares[id(c)] for c in group[1:]],
             "separated_by": {c.effect: sep.get(c.effect, "") for c in group}}]


def lookalike_words(groups: list[dict]) -> list[str]:
    """The look-alike groups in words: which effects, how close, and what would separate them."""
    out = []
    for g in groups:
        first, others = g["effects"][0], g["effects"][1:]
        out.append(f"Look-alikes: {', '.join(others)} explain{'s' if len(others) == 1 else ''} the data about as "
                   f"well as {first} (delta BIC " + ", ".join(f"{b:.1f}" for b in g["delta_bic"]) +
                   f": {g['closer_than']}); {first} is named on the evidence at hand, but this log does not "
                   "separate them firmly. What would: " + "; ".join(
                       f"for {e}, {w}" for e, w in g["separated_by"].items() if w) + ".")
    return out


def strong_structures(structure: list[dict], options: DiagnoseOptions = DEFAULTS) -> list[dict]:
    """The residual structures at least ``options.structure_share`` as strong as the strongest."""
    return [s for s in structure if s["strength"] >= options.structure_share * structure[0]["strength"]]


def own_structure(c, explains: dict, report: dict, structure: list[dict],
                  options: DiagnoseOptions = DEFAULTS) -> dict | None:
    """The strongest residual structure among ``c``'s own (channel, covariate) pairs (its class's ``explains``) in the
    channel ``report``, each tested at ``options.structure_p`` times the tests the report ran over the pairs of ``c``
    it ran: the material ``structure`` is a search over every pair, a candidate's corroboration a test of its few,
    and both then keep one family-wise error. Strong enough to count (``structure_omega2``, and ``structure_share``
    of the strongest material structure, unless a motion pair against place holds across the robot's visits
    below ``options.visit_strong_p`` over the own pairs so tested), not the closed loop's ``feedback``, and a
    motion pair against place holding across the robot's visits (``visits_p`` below ``options.visit_p``); None
    when none passes, or when ``c`` has held-out folds (they are its second line) or ``options.own_structure`` is
    off."""
    if not options.own_structure or c.heldout_skipped != NO_FOLDS or not report:
        return None
    own, p = own_pairs(c, explains, report, options)
    floor = max(options.structure_omega2, options.structure_share * (structure[0]["strength"] if structure else 0.0))
    strong_visits = options.visit_strong_p / max(sum("visits_p" in t for _, t in own), 1)
    found = [{"channel": ch, **t, "p_threshold": p} for ch, t in own
             if t["p"] < p and t["kind"] != "feedback" and repeats(t, options.visit_p)
             and (t["strength"] >= floor or t.get("visits_p", 1.0) < strong_visits)]
    return max(found, key=lambda t: t["strength"]) if found else None


def own_pairs(c, explains: dict, report: dict, options: DiagnoseOptions = DEFAULTS) -> tuple[list, float]:
    """(channel, test) of each of ``c``'s own pairs the channel ``report`` ran (its covariate tests and trends), and
    the p they are tested at: ``options.structure_p`` times the report's tests over the own pairs among them (one
    family-wise error)."""
    tests = [(ch, t) for ch, r in report.items()
             for t in r.get("covariates", []) + ([r["trend"]] if "trend" in r else [])]
    own = [(ch, t) for ch, t in tests if (ch, t["name"]) in tuple(explains.get(c.effect, ()))]
    return own, options.structure_p * len(tests) / max(len(own), 1)


def repeats(test: dict, visit_p: float) -> bool:
    """Whether a covariate test holds across the robot's visits (``visits_p`` below ``visit_p``); True when it was
    not tested so (not a motion pair against place, too few visits) or ``visit_p`` is 0 (the test off)."""
    return visit_p <= 0 or "visits_p" not in test or test["visits_p"] < visit_p


def holds_across_visits(report: dict | None, channel: str, covariate: str, visit_p: float) -> bool:
    """Whether the ``channel`` residuals' dependence on ``covariate`` holds across the robot's visits, as the channel
    ``report`` tested it (``visits_p`` below ``visit_p``); True for a covariate that is not a place, one not
    tested so, or ``visit_p`` 0 (the test off)."""
    if covariate not in PLACE_COVARIATES or not report:
        return True
    t = next((t for t in report.get(channel, {}).get("covariates", []) if t["name"] == covariate), None)
    return t is None or repeats(t, visit_p)


def place_repeats(c, explains: dict, report: dict | None, options: DiagnoseOptions = DEFAULTS) -> bool:
    """Whether one of ``c``'s own motion pairs against place, significant at its own pairs' level (as
    :func:`own_structure` tests them), holds across the robot's visits; True without a ``report`` or with
    ``options.visit_p`` 0."""
    if not report or options.visit_p <= 0:
        return True
    own, p = own_pairs(c, explains, report, options)
    return any(t["p"] < p and "visits_p" in t and repeats(t, options.visit_p) for _, t in own)


def built_for(strong: list[dict], explains: dict, report: dict | None = None, structure: list[dict] = (),
              options: DiagnoseOptions = DEFAULTS) -> Callable:
    """Whether a candidate is the effect built for one of the ``strong`` structures (its class's ``explains``), or,
    given the channel ``report``, for a structure of its own (:func:`own_structure`). A strong motion structure
    against place counts only when one of the candidate's own place pairs holds across the robot's visits
    (:func:`place_repeats`): the strongest pair may follow the poses' wander while a weaker one carries the floor
    (the omni world's carpet seed 4: turn residuals against place, p 1e-16, across visits 0.8; forward against x
    across visits 0.003)."""
    def matches(c) -> bool:
        return (any((s["channel"], s["name"]) in tuple(explains.get(c.effect, ()))
                    and ("visits_p" not in s or place_repeats(c, explains, report, options)) for s in strong)
                or own_structure(c, explains, report, structure, options) is not None)
    return matches


def is_supported(c: Candidate, matches: Callable, options: DiagnoseOptions = DEFAULTS) -> bool:
    """BIC supports ``c`` strongly and a second line agrees: the held-out score, or the structure it is built for
    unless the held-out score speaks against it (falls by more than ``options.heldout_veto`` nats)."""
    return not c.implausible and c.delta_bic <= options.bic_support and (
        c.heldout_nll_drop > options.heldout_support
        or (matches(c) and not c.heldout_nll_drop < -options.heldout_veto))


def taking_away(gaining: list[Candidate], s: dict, refit: Callable | None,
                options: DiagnoseOptions = DEFAULTS) -> Candidate | None:
    """The first of the ``options.refit_candidates`` candidates of ``gaining`` (those lowering BIC strongly,
    plausible, the lowest delta BIC first) with the held-out score not against it whose refit on the log
    (``refit``: a candidate -> the channel report with its fit, or None) leaves the residual structure ``s`` no
    longer material (:func:`structures`) with at most ``options.refit_share`` of its strength, its ``takes_away``
    saying so; None when none does. A structure an effect's fit takes away is that effect's, whatever covariate the
    bins saw it through (a floor the robot crosses in stretches of the log shows against time)."""
    if refit is None or options.refit_candidates <= 0:
        return None
    for c in [c for c in gaining if not c.heldout_nll_drop < -options.heldout_veto][:options.refit_candidates]:
        rep = refit(c)
        after = next((t for t in (rep or {}).get(s["channel"], {}).get("covariates", []) if t["name"] == s["name"]),
                     None)
        if (after is None or after["strength"] > options.refit_share * s["strength"]
                or any((m["channel"], m["name"]) == (s["channel"], s["name"]) for m in structures(rep, options))):
            continue
        c.takes_away = {"channel": s["channel"], "covariate": s["name"], "strength": s["strength"], "p": s["p"],
                        "strength_after": after["strength"], "p_after": after["p"]}
        return c
    return None


def verdict(cands: list[Candidate], structure: list[dict], explains: dict | None = None,
            options: DiagnoseOptions = DEFAULTS, last: tuple = (), report: dict | None = None,
            refit: Callable | None = None) -> tuple[str, list[str]]:
    """The verdict and the sentences that explain it.

    A candidate is supported when BIC supports it strongly and a second, independent line agrees:
    the held-out log-likelihood improves, or the candidate is the effect built for a strong residual
    structure (its ``explains`` holds the channel and covariate of one at least ``options.structure_share``
    as strong as the strongest). Among supported
    candidates whose delta BIC is within ``options.bic_tie`` of the lowest (no evidence either way on
    Kass and Raftery's scale; look-alikes such as a weak actuator lag and camera latency) the
    held-out score decides. Effects named in ``last`` are the verdict only when no other candidate is supported
    (a continuous log's false-detection mixture, scored on the sightings the gate sets aside, whose delta BIC is
    not on the others' scale: a strong lens sends sightings beyond the gate too). Given the channel ``report``, a
    candidate without held-out folds may also be built for a structure of its own (:func:`own_structure`). A
    candidate whose fit cannot happen (``implausible``) is set aside, and the words say so. With none supported so,
    a candidate whose refit (``refit``) takes away the strongest structure that holds across the robot's visits is
    (:func:`taking_away`). With no candidate supported, the verdict is ``unexplained:`` that structure
    (:func:`repeats`), else ``none``: a motion dependence on place that each visit shows with its own offset is the
    slip's wander, not something the model lacks (the wheel world's effect-free seed 0: lateral residuals against
    place, p 3e-30, across its 32 visits p 0.17)."""
    words = []
    explains = explains or {}
    o = options
    strong = strong_structures(structure, o)
    matches = built_for(strong, explains, report, structure, o)
    supported = [c for c in cands if is_supported(c, matches, o)]
    lasting = [s for s in structure if repeats(s, o.visit_p)]
    gaining = sorted((c for c in cands if c.delta_bic <= o.bic_support and not c.implausible),
                     key=lambda c: c.delta_bic)
    if not supported and lasting:
        supported = [c for c in [taking_away(gaining, lasting[0], refit, o)] if c is not None]
    aside = [f"{SET_ASIDE}: {c.effect} lowers BIC by {-c.delta_bic:.1f}, but its fit says {c.implausible}; "
             "it bends that effect's form around structure of another kind." for c in cands
             if c.implausible and c.delta_bic <= o.bic_support]
    first = [c for c in supported if c.effect not in last] or supported
    if supported:
        lead = min(c.delta_bic for c in first)
        tied = [c for c in first if c.delta_bic - lead < o.bic_tie]
        best = max(tied, key=lambda c: -np.inf if np.isnan(c.heldout_nll_drop) else c.heldout_nll_drop)
        if best.heldout_nll_drop > o.heldout_support:
            second = f"improves the held-out log-likelihood by {best.heldout_nll_drop:.1f} nats"
        elif best.takes_away:
            a = best.takes_away
            second = (f"its fit takes away the strongest residual structure that holds across the robot's visits "
                      f"({a['channel']} residuals against {a['covariate']}: {100 * a['strength']:.1f} % of their "
                      f"variance, p = {a['p']:.1e}; with it {100 * a['strength_after']:.1f} %, p = "
                      f"{a['p_after']:.1e}), a covariate it is not built for: the structure is this effect's, seen "
                      f"through another covariate")
        else:
            s = next((s for s in strong if (s["channel"], s["name"]) in tuple(explains.get(best.effect, ()))), None)
            held = (f"though the held-out score does not improve ({best.heldout_nll_drop:.1f} nats)"
                    if np.isfinite(best.heldout_nll_drop) else f"its held-out score not measured ({best.heldout_skipped})")
            if s is not None:
                rank = "the strongest" if s is structure[0] else "a strong"
                second = f"accounts for {rank} residual structure ({s['channel']} residuals against {s['name']}), {held}"
            else:
                s = own_structure(best, explains, report, structure, o)
                what = (f"the share of its modelled {s['channel']} motion the robot achieved changes "
                        f"{100 * s['rate']:+.2f} % per minute, t = {s['t']:.1f}" if s["kind"] == "scale" else
                        f"{s['channel']} residuals against {s['name']}")
                second = (f"accounts for a residual structure it is built for ({what}: "
                          f"{100 * s['strength']:.1f} % of their variance, p = {s['p']:.1e}, below "
                          f"{s['p_threshold']:.1e} for a test of its own pairs"
                          + (f"; it holds across the robot's {s['visits']} visits, p = {s['visits_p']:.1e}"
                             if "visits_p" in s else "") + f"), {held}")
        words.append(f"The residuals point to {best.effect}: adding it lowers BIC by {-best.delta_bic:.1f} "
                     f"and {second}. {best.explanation}")
        if len(tied) > 1:
            words.append("BIC cannot tell " + " and ".join(c.effect for c in tied) + " apart (delta BIC "
                         + ", ".join(f"{c.delta_bic:.1f}" for c in tied) + f": closer than {o.bic_tie:g}); the "
                         "held-out log-likelihood prefers " + best.effect + " (" + ", ".join(
                             f"{c.heldout_nll_drop:.1f}" for c in tied) + " nats).")
        rest = [c for c in first if c is not best]
        if rest:
            words.append("Also supported, less strongly: " + ", ".join(
                f"{c.effect} (delta BIC {c.delta_bic:.1f})" for c in rest) + ".")
        later = [c for c in supported if c not in first]
        if later:
            words.append("Also supported, after the effects with a structure: " + ", ".join(
                f"{c.effect} (delta BIC {c.delta_bic:.1f})" for c in later) + "; the sightings it calls false may be "
                "ones the verdict's effect explains: diagnose again once that is added.")
        unscored = [c for c in cands if c.heldout_skipped == DECIDED and c.delta_bic <= o.bic_support
                    and c not in supported]
        if unscored:
            words.append("Also lowering BIC strongly, not scored on held-out folds (the verdict does not depend on "
                         "them): " + ", ".join(f"{c.effect} (delta BIC {c.delta_bic:.1f})" for c in unscored) + ".")
        return best.effect, words + aside
    named = ", ".join(f"{c.effect} (delta BIC {c.delta_bic:.1f})" for c in gaining[:3])
    if lasting:
        s = lasting[0]
        words.append(f"No catalog effect explains the data better, but the {s['channel']} residuals' "
                     f"{s['kind']} follows {s['name']} (it explains {100 * s['strength']:.1f} % of their variance, "
                     f"p = {s['p']:.1e}). Something the model and the catalog lack depends on {s['name']}.")
        if gaining:
            words.append(f"Catalog effects lower BIC without a second line: {named}; none is named on BIC alone, "
                         f"which a flexible effect earns by following slow wander. The structure may still be one of "
                         f"them seen through a covariate it is not built for (a floor the robot crosses in stretches "
                         f"of the log shows against time): a longer log, more visits to each place, would give it "
                         f"the second line it lacks.")
        if s["channel"] == "reading" and s["name"] == "distance":
            words.append("The sensor curve itself may be what misses: a reading that is an apparent size (pixels) "
                         "falls as 1/distance, which a polynomial in the distance follows badly near the landmarks; "
                         "calibrate again with --sensor-basis inverse_distance (or a higher --max-sensor-degree).")
        return f"unexplained:{s['name']}", words + aside
    quiet = "no channel's residuals depend materially on any covariate" + (
        " that holds across the robot's visits" if structure else "")
    if gaining:
        words.append(f"The model explains the data: {named} lower BIC, but no second line agrees (no held-out gain, "
                     f"no residual structure they are built for), and {quiet}. A flexible effect lowers BIC by "
                     "following the motion noise's slow wander, which BIC scores as if each step's noise were "
                     "independent.")
    else:
        words.append("The model explains the data: no candidate effect lowers BIC by more than "
                     f"{-o.bic_support:g} and {quiet}.")
    if structure:                    # every structure fails the visits test: the strongest is the slip's wander
        s = structure[0]
        words.append(f"The {s['channel']} residuals depend on {s['name']} ({100 * s['strength']:.1f} % of their "
                     f"variance, p = {s['p']:.1e}), but not across the robot's {s['visits']} visits to each place (p = "
                     f"{s['visits_p']:.2f}): each pass has its own offset, as slip that wanders for seconds leaves, "
                     "where a floor slows the robot on every pass.")
    return "none", words + aside


@dataclass
class Diagnosis:
    channels: dict
    candidates: list[Candidate]
    verdict: str
    words: list[str]
    structure: list[dict]
    base: object
    residuals: dict
    seconds: float
    skipped: dict
    set_aside: int = 0               # sightings left out as gross outliers (continuous logs; an action table's
    #                                  diagnosis keeps them: a few wild sightings are what false_detections models)
    correlation: dict = field(default_factory=dict)   # residual auto- and cross-correlation (analysis.correlation)
    lookalikes: list = field(default_factory=list)    # candidates as good as the verdict's effect (:func:`lookalikes`)
    before_after: dict | None = None  # the change from an earlier diagnosis (analysis.before_after.compare)
    predictive: dict = field(default_factory=dict)    # open-loop prediction error per horizon (analysis.predictive)
    proposal: dict = field(default_factory=dict)      # an effect equation for unexplained motion structure (analysis.proposal)
    options: DiagnoseOptions = DEFAULTS               # how it was diagnosed (diagnosis.json ``options``)
    log: Log | None = None           # the log diagnosed (its report needs it)
    write_report: Callable | None = field(default=None, repr=False)   # (path, log, diagnosis): the report page

    def to_json(self) -> dict:
        return {"schema": SCHEMA, "channels": self.channels,
                "candidates": [c.to_json() for c in self.candidates], "verdict": self.verdict,
                "summary": self.words, "not_applicable": self.skipped,
                "base": {"log_likelihood": self.base.log_likelihood, "effects": self.base.model.effects},
                "sightings_set_aside": self.set_aside, "lookalikes": self.lookalikes,
                "correlation": self.correlation, "predictive": self.predictive,
                **({"proposal": self.proposal} if self.proposal else {}), "options": self.options.to_json(),
                **({"before_after": self.before_after} if self.before_after else {}),
                "seconds": round(self.seconds, 2)}

    def summary(self) -> str:
        """The verdict and the reasons, as ``casm-graph diagnose`` prints them."""
        aside = [f"{self.set_aside} sighting(s) set aside as gross outliers"] if self.set_aside else []
        said = [w for w in (proposal_words(self.proposal), predictive_words(self.predictive)) if w]
        return "\n".join([f"verdict: {self.verdict}  ({self.seconds:.0f} s)",
                          *("  " + w for w in self.words + aside + said + self.change_lines())])

    def change_lines(self) -> list[str]:
        """The change from the earlier diagnosis (``before``), a line per channel, in words."""
        ba = self.before_after
        if not ba:
            return []
        (v0, v1), (e0, e1), (l0, l1) = ba["verdict"], ba["effects"], ba["log_likelihood"]
        lines = [f"Since the earlier diagnosis (verdict {v0}, effects {', '.join(e0) or 'none'}): verdict {v1}, "
                 f"effects {', '.join(e1) or 'none'}" + (f", log-likelihood {l0:.1f} -> {l1:.1f}"
                                                         if l0 is not None and l1 is not None else "") + "."]
        for ch, row in ba["channels"].items():
            r0, r1 = row["rms_raw"]
            words = f"  {ch}: residual RMS {r0:.4g} -> {r1:.4g}" if r0 is not None and r1 is not None else f"  {ch}:"
            cov = row.get("covariate")
            if cov and None not in cov["strength"]:
                words += f"; {cov['kind']} vs {cov['name']} explained {100 * cov['strength'][0]:.1f} % -> " \
                         f"{100 * cov['strength'][1]:.1f} %"
            lines.append(words)
        pred = ba.get("predictive")
        if pred and pred["channels"]:
            i = len(pred["horizons_s"]) - 1
            lines.append(f"  predicted {pred['horizons_s'][i]:g} s ahead: " + ", ".join(
                f"{ch} {v[0][i]:.4g} -> {v[1][i]:.4g}" for ch, v in pred["channels"].items()))
        return lines

    def to_add(self) -> str | None:
        """What ``calibrate --effect`` takes to add the verdict's effect (``name:order`` for a family), or None."""
        return next((c.spec for c in self.candidates if c.effect == self.verdict), None)

    def proposal_effect(self) -> type:
        """The effect class of the proposal (``cg.calibrate(log, effects=[diag.proposal_effect()])``)."""
        if not self.proposal:
            raise LogError(f"no effect was proposed (verdict {self.verdict}): a proposal comes with an "
                           "'unexplained:<covariate>' verdict whose motion residuals a library term explains")
        return proposal_effect(self.proposal["terms"])

    def save(self, out, force: bool = False) -> Path:
        """Write DIAG (diagnosis.json, report.html) all or nothing; ``out`` must be new or empty."""
        with atomic_dir(out, force=force, inputs=[self.log.source] if self.log.source else []) as tmp:
            (tmp / "diagnosis.json").write_text(json_text(self.to_json()))
            if self.write_report is not None:
                self.write_report(tmp / "report.html", self.log, self)
        return Path(out)


def chosen_candidates(candidates, extra_effects=()) -> set | None:
    """The effect names a diagnosis is asked to try (None: every applicable one); an unknown name is one LogError."""
    if candidates is None:
        return None
    known = {*REGISTRY, *(cls.name for cls in extra_effects)}
    unknown = sorted(set(candidates) - known)
    if unknown:
        raise LogError(f"unknown candidate effect(s) {unknown} (known: {', '.join(sorted(known))})")
    return set(candidates)


def discover(verdict_name: str, words: list[str], chs: dict, options: ProposalOptions, cands=(),
             explains: dict | None = None, support: float = DEFAULTS.bic_support,
             challenge: Callable | None = None, ratio: float = 0.0,
             margin: float = DEFAULTS.lookalike_bic, report: dict | None = None,
             visit_p: float = 0.0, structure: list[dict] = ()) -> tuple[str, list[str], dict]:
    """The verdict, its words and the sparse-regression proposal (:func:`casm_graph.analysis.proposal.propose`,
    searching as ``options`` say). An ``unexplained:<covariate>`` verdict gets the proposal; so does ``none``
    when the regression finds terms that pass its own test, and the verdict becomes ``unexplained:`` the strongest
    term's covariate: the covariate tests bin one covariate at a time and miss a dependence on heading that the
    trajectory's smoothing spreads thin, which a term such as ``v_forward*sin(heading)`` catches, when its strongest
    term reaches ``options.last_test_t``. That last test leaves out the oscillations in time: the best of forty
    periods passed |t| = 5 on slow drift of effect-free smoothed trajectories, and a time dependence that matters
    shows in the covariate tests' time bins.

    Terms that pass are a residual structure too: a candidate of ``cands`` with delta BIC at most ``support``
    whose held-out score was not measured (continuous commands) and that ``explains`` (by name) a term's axis and
    covariate is named instead, the lowest delta BIC first (a weak battery fade: no bin of time stood out, the
    regression's slow trend in time did). A term in a place covariate is structure only when the channel
    ``report``'s test of it holds across the robot's visits (:func:`holds_across_visits` at ``visit_p``), for a
    candidate and for the ``unexplained:`` verdict alike (whose strongest term it would be). An ``unexplained:``
    verdict on a motion channel's ``structure`` takes the covariate of the proposal's strongest term on that channel
    when it differs and holds: the regression weighs every term together, the bins one covariate at a time; with no
    term at all, that structure is the slip's wander and the verdict none (:func:`formless`)."""
    if verdict_name.startswith("unexplained:"):
        found = propose(chs, options)
        wander = formless(verdict_name, words, found, structure, visit_p, options)
        return (*(wander or attributed(verdict_name, words, found, structure, report, visit_p)), found)
    if verdict_name != "none":
        return challenged(verdict_name, words, chs, options, cands, challenge, ratio, margin)
    found = propose(chs, replace(options, periods=0))
    if not found:
        return verdict_name, words, {}
    terms = term_covariates(found)
    backing = [t for t in terms if holds_across_visits(report, t[0], t[1], visit_p)]
    built = [c for c in sorted(cands, key=lambda c: c.delta_bic) if c.delta_bic <= support and not c.implausible
             and np.isnan(c.heldout_nll_drop) and any(t in tuple((explains or {}).get(c.effect, ())) for t in backing)]
    if built:
        c = built[0]
        axis, cov = next(t for t in backing if t in tuple(explains[c.effect]))
        return c.effect, [
            f"The residuals point to {c.effect}: adding it lowers BIC by {-c.delta_bic:.1f}, and a sparse regression "
            f"of the motion residuals finds the {axis} residuals depending on {cov} (|t| >= {options.min_t:g}), the "
            f"structure it is built for. {c.explanation}"] + set_aside_words(words), {}
    if terms[0] not in backing or strongest_t(found) < options.last_test_t:
        return verdict_name, words, {}
    cov = terms[0][1]
    return f"unexplained:{cov}", [
        "No catalog effect is supported and no single covariate's bins show material structure, but a sparse "
        f"regression of the motion residuals finds terms that pass its test (|t| >= {options.min_t:g}): something "
        f"the model and the catalog lack depends on {cov}."] + set_aside_words(words), found


def verdict_structure(verdict_name: str, structure: list[dict], visit_p: float) -> tuple[str, dict | None]:
    """(the covariate of an ``unexplained:<covariate>`` verdict, the first structure in it of ``structure`` that holds
    across the robot's visits at ``visit_p``, or None)."""
    named = verdict_name.partition(":")[2]
    return named, next((s for s in structure if s["name"] == named and repeats(s, visit_p)), None)


def formless(verdict_name: str, words: list[str], found: dict, structure: list[dict], visit_p: float,
             options: ProposalOptions) -> tuple[str, list[str]] | None:
    """``none`` and its words when the ``unexplained:<covariate>`` verdict's structure (the first of ``structure`` in
    that covariate holding across visits at ``visit_p``) is a motion channel's and the sparse regression found no
    term at all (``found`` empty, ``options.needs_form``): a dependence no term of its library follows (the
    covariates, their products, oscillations in time) is the slip's slow wander (car world, the lag added: lateral
    residuals against time, 1.5 % of their variance, p 1e-15; the wheel world's effect-free seed 0 alike), where the
    uncataloged effects of the test worlds each had their terms; None otherwise."""
    named, s = verdict_structure(verdict_name, structure, visit_p)
    if not options.needs_form or found or s is None or s["channel"] not in MOTION_CHANNELS:
        return None
    return "none", [
        f"The model explains the data: the {s['channel']} residuals' {s['kind']} follows {named} "
        f"({100 * s['strength']:.1f} % of their variance, p = {s['p']:.1e}), but a sparse regression of the motion "
        f"residuals finds no term that follows it (the covariates, their products, oscillations in time: none reaches "
        f"|t| = {options.min_t:g}). A dependence without a form is the slip's slow wander over the log, not an effect "
        f"the model lacks."] + set_aside_words(words)


def attributed(verdict_name: str, words: list[str], found: dict, structure: list[dict], report: dict | None,
               visit_p: float) -> tuple[str, list[str]]:
    """An ``unexplained:<covariate>`` verdict and its words, the covariate that of the proposal's strongest term on
    the same channel when the verdict's structure (the first of ``structure`` in that covariate holding across
    visits at ``visit_p``) is a motion channel's and that term's covariate differs and holds across the robot's
    visits too (:func:`holds_across_visits`): a robot whose speed changes along the log shows a turn rate that
    grows with speed against time as well (continuous world, seed 1: turn residuals against time, 1.3 % of their
    variance; the proposal turn += 0.126 speed, |t| 6.9). A term on another channel is another structure."""
    named, s = verdict_structure(verdict_name, structure, visit_p)
    if not found or s is None or s["channel"] not in MOTION_CHANNELS:
        return verdict_name, words
    cov = next((c for a, c in term_covariates(found) if a == s["channel"]), named)
    if cov == named or not holds_across_visits(report, s["channel"], cov, visit_p):
        return verdict_name, words
    t = max(abs(v) for v in found["axes"][s["channel"]]["t_values"].values())
    return f"unexplained:{cov}", words + [
        f"A sparse regression of the motion residuals, every term weighed together, puts the {s['channel']} "
        f"structure on {cov} (its strongest term there, |t| = {t:.1f}); the dependence on {named} the bins show "
        f"comes with it."]


def challenged(verdict_name: str, words: list[str], chs: dict, options: ProposalOptions, cands, challenge,
               ratio: float, margin: float) -> tuple[str, list[str], dict]:
    """A catalog verdict against the sparse regression's proposal: ``challenge`` fits the proposal's effect class
    as a candidate on the verdict's footing and returns its (log-likelihood gain, delta BIC). When the proposal
    gains at least ``ratio`` times the verdict's gain and its delta BIC is more than ``margin`` lower, the catalog
    effect explains only part of the structure and the verdict becomes ``unexplained:`` the proposal's strongest
    covariate, with the proposal (and its fitted gain) to add. A catalog effect of the right form gains about what
    the proposal's terms gain (a fade's exponential in time, a linear term in time) and stays. Only a verdict on
    the motion channel is challenged: the proposal's terms are motion terms, and what they gain does not compete
    with a sensor effect's gain on the sightings (a continuous world's range-dependent noise, 836 nats, lost to a
    turn rate oscillating in time that gained 2,321 on the world's slip)."""
    named = next((c for c in cands if c.effect == verdict_name), None)
    if challenge is None or ratio <= 0 or named is None or named.channel != "motion":
        return verdict_name, words, {}
    found = propose(chs, options)
    if not found:
        return verdict_name, words, {}
    gain, dbic = challenge(proposal_effect(found["terms"]))
    if not (gain >= ratio * max(named.delta_log_likelihood, 0.0) and dbic < named.delta_bic - margin):
        return verdict_name, words, {}
    found = {**found, "fitted": {"delta_log_likelihood": float(gain), "delta_bic": float(dbic),
                                 "instead_of": {"effect": named.effect, "delta_bic": named.delta_bic,
                                                "delta_log_likelihood": named.delta_log_likelihood}}}
    cov = term_covariates(found)[0][1]
    return f"unexplained:{cov}", [
        f"The best catalog effect, {named.effect} (delta BIC {named.delta_bic:.1f}), explains only part of the "
        f"residual structure: the sparse regression's proposal, fitted as an effect, gains {gain:.1f} nats against "
        f"its {named.delta_log_likelihood:.1f} (delta BIC {dbic:.1f}). Something the catalog lacks depends on "
        f"{cov}."], found


def open_loop_error(problem, st, poses: np.ndarray) -> dict:
    """:func:`casm_graph.analysis.predictive.predictive` of the refitted model from ``poses`` (T+1, 3, the smoothed
    trajectory at every step), any action model: its motion effects drive the open-loop runs, its sensor effects
    predict the sightings (those the problem takes: a mixture's outliers and the gate's left out)."""
    knots = problem.lay.knots

    def residuals(trajectory):
        terms = problem.observation_terms(replace(st, poses=trajectory[knots]))
        return {ch: np.where(sel & (terms["weight"] > 0.5), terms[ch], np.nan)
                for ch, sel in (("reading", problem.r_sel), ("bearing", problem.b_sel))}
    return predictive(poses, problem.action.step_velocities(st.poses, st.action, st.theta), problem.log.dt,
                      residuals, lead=problem.action.lead)
