"""Posterior of the noise levels by emcee under their marginal likelihood, and its summary.

The sampler works in coordinates u: log sigma for every noise level that is a scale, the raw
value for effect parameters. Priors (stated in posterior.json, overridable with ``--prior``):

* every sigma (reading, bearing, motion per axis): log-normal around the calibrated model's value
  with a standard deviation of 1 in log (a factor e): weakly informative, flat on the scale of
  any likelihood that pins a level down (the sensor sigmas to a few per cent), but it keeps a
  level the log cannot tell from zero within a factor of a few of the calibration. A log-uniform
  prior over decades looks vaguer but is not: where the likelihood is flat (per-step motion
  noise below what the sightings resolve) it puts the same mass on every decade, the posterior
  piles up at implausibly small noise, and the velocity table's intervals, which scale with
  the motion noise, become overconfident (w intervals covered the truth 71 % of the time
  instead of 90 % in benchmarks/coverage.py);
* ``range_dependent_noise.growth``: uniform on [0, 5] per metre; ``false_detections.fraction``:
  uniform on [0, 0.5].

The likelihood is either of :mod:`casm_graph.analysis.likelihood` (action table or
continuous commands): the sampler sees only its noise levels, so a sensor channel the log does not
measure has no sigma here and no prior.

Run length follows emcee's integrated autocorrelation time tau: chunks of steps until the
chain is at least ``SamplerOptions.tau_factor`` tau long with tau settled, burn-in is a few tau, samples are
thinned to about tau/2. A chain stopped by ``max_steps`` first is flagged too short (warning).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass, field

import emcee
import numpy as np
from scipy.optimize import minimize

from casm_graph.analysis.likelihood import NoiseLikelihood
from casm_graph.io.log import LogError



@dataclass(frozen=True)
class SamplerOptions:
    """How long emcee runs, what it keeps, and how many of its draws the Laplace marginals average over;
    recorded in posterior.json ``sampler.options``."""

    walkers: int | None = None     # None: max(2 d + 2, 12) for d noise levels
    max_steps: int = 5000
    min_steps: int = 300
    tau_factor: float = 50.0       # emcee's advice: a chain of at least 50 tau
    check_every: int = 100         # steps between autocorrelation checks
    burn_taus: float = 3.0         # burn-in, in tau
    target_samples: int = 500      # independent samples wanted: 25 beyond each end of a 90 % interval (coverage +-1.5 %)
    draws: int = 64                # posterior noise draws the table's and polynomial's Laplace marginals are averaged over

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class Prior:
    """A prior on one noise level: ``loguniform``, ``uniform``, ``lognormal`` or ``normal``."""

    kind: str
    a: float
    b: float

    def describe(self) -> str:
        return {"loguniform": f"log-uniform on [{self.a:.4g}, {self.b:.4g}]",
                "uniform": f"uniform on [{self.a:.4g}, {self.b:.4g}]",
                "lognormal": f"log-normal, median {self.a:.4g}, sd of log {self.b:.4g}",
                "normal": f"normal, mean {self.a:.4g}, sd {self.b:.4g}"}[self.kind]

    def log_density(self, x: float, u: float, log_coord: bool) -> float:
        """log prior density in the sampling coordinate u (x = exp(u) when ``log_coord``)."""
        jac = u if log_coord else 0.0                     # dx = x du
        if self.kind == "loguniform":
            return (0.0 if log_coord else -math.log(x)) if self.a <= x <= self.b else -np.inf
        if self.kind == "uniform":
            return jac if self.a <= x <= self.b else -np.inf
        if self.kind == "lognormal":
            if x <= 0:
                return -np.inf
            return -0.5 * ((math.log(x) - math.log(self.a)) / self.b) ** 2 - (0.0 if log_coord else math.log(x))
        return -0.5 * ((x - self.a) / self.b) ** 2 + jac

    def bounds(self) -> tuple[float, float]:
        if self.kind in ("loguniform", "uniform"):
            return self.a, self.b
        if self.kind == "lognormal":
            return 0.0, np.inf
        return -np.inf, np.inf


def parse_prior(spec: str) -> tuple[str, Prior]:
    """``NAME=KIND:A:B`` (e.g. ``reading_sigma=lognormal:1.0:0.3``) as (name, Prior)."""
    name, sep, rest = spec.partition("=")
    parts = rest.split(":")
    if not sep or len(parts) != 3 or parts[0] not in ("loguniform", "uniform", "lognormal", "normal"):
        raise LogError(f"--prior {spec!r}: expected NAME=KIND:A:B with KIND loguniform, uniform, lognormal or normal")
    try:
        a, b = float(parts[1]), float(parts[2])
    except ValueError:
        raise LogError(f"--prior {spec!r}: A and B must be numbers") from None
    if not (np.isfinite(a) and np.isfinite(b)) or (parts[0] in ("loguniform", "uniform") and not a < b) \
            or (parts[0] == "loguniform" and a <= 0) or (parts[0] in ("lognormal", "normal") and b <= 0) \
            or (parts[0] == "lognormal" and a <= 0):
        raise LogError(f"--prior {spec!r}: bad parameters for a {parts[0]} prior")
    return name.strip(), Prior(parts[0], a, b)


def default_priors(ml: NoiseLikelihood) -> dict[str, Prior]:
    out = {}
    for p in ml.params:
        if p.kind != "effect":
            out[p.name] = Prior("lognormal", p.value, 1.0)
        elif p.name.endswith("fraction"):
            out[p.name] = Prior("uniform", 0.0, 0.5)
        else:
            out[p.name] = Prior("uniform", 0.0, 5.0)
    return out


def priors_for(ml: NoiseLikelihood, overrides: dict[str, Prior] | None = None) -> dict[str, Prior]:
    pri = default_priors(ml)
    for name, pr in (overrides or {}).items():
        if name not in pri:
            raise LogError(f"--prior {name!r}: not a noise level of this model (known: {', '.join(pri)})")
        pri[name] = pr
    return pri


class LogPosterior:
    """log p(u | O) up to a constant, in the sampler's coordinates; counts and times its evaluations."""

    def __init__(self, ml: NoiseLikelihood, priors: dict[str, Prior]):
        self.ml, self.priors = ml, [priors[n] for n in ml.names]
        self.log_coord = np.array([p.kind != "effect" for p in ml.params])
        self.evaluations, self.seconds, self.cpu_seconds = 0, 0.0, 0.0

    def __call__(self, u) -> float:
        t0, c0 = time.perf_counter(), time.process_time()
        x = self.ml.natural(u)
        lp = 0.0
        for pr, xi, ui, lc in zip(self.priors, x, u, self.log_coord):
            lp += pr.log_density(float(xi), float(ui), bool(lc))
        if np.isfinite(lp):
            lp += self.ml(x)
        self.evaluations += 1
        self.seconds += time.perf_counter() - t0
        self.cpu_seconds += time.process_time() - c0
        return float(lp) if np.isfinite(lp) else -np.inf


def find_mode(post: LogPosterior, u0: np.ndarray, h: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mode (Powell from ``u0``) and the covariance from a finite-difference Hessian there.

    Directions the log hardly constrains get a large but finite variance (at most 1 in u), so the
    walkers start spread along them instead of collapsing.
    """
    res = minimize(lambda u: -post(u), u0, method="Powell", options={"xtol": 1e-3, "ftol": 1e-3, "maxfev": 400})
    u = res.x if np.isfinite(res.fun) and res.fun <= -post(u0) else np.asarray(u0, float)
    d = len(u)
    f0 = post(u)
    Hs = np.zeros((d, d))
    E = np.eye(d) * h
    fp = np.array([post(u + E[i]) for i in range(d)])
    fm = np.array([post(u - E[i]) for i in range(d)])
    for i in range(d):
        Hs[i, i] = (fp[i] - 2 * f0 + fm[i]) / h ** 2
        for j in range(i):
            fpp, fmm = post(u + E[i] + E[j]), post(u - E[i] - E[j])
            Hs[i, j] = Hs[j, i] = (fpp - fp[i] - fp[j] + 2 * f0 - fm[i] - fm[j] + fmm) / (2 * h ** 2)
    if not np.all(np.isfinite(Hs)):
        return u, np.eye(d) * 0.01
    w, V = np.linalg.eigh(-Hs)
    w = np.maximum(w, 1.0)                               # sd at most 1 along flat directions
    return u, (V / w) @ V.T


@dataclass
class Chain:
    """The sampler's output: the kept samples (natural units), the full chain and its diagnostics."""

    names: list
    samples: np.ndarray               # (n, d) after burn-in and thinning, natural units
    chain: np.ndarray                 # (steps, walkers, d) natural units
    log_prob: np.ndarray              # (steps, walkers)
    walkers: int
    steps: int
    burn_in: int
    thin: int
    tau: np.ndarray
    acceptance: float
    too_short: bool
    mode: np.ndarray
    evaluations: int
    seconds_per_evaluation: float
    cpu_seconds_per_evaluation: float = float("nan")
    notes: list = field(default_factory=list)


def run(ml: NoiseLikelihood, priors: dict[str, Prior], options: SamplerOptions | None = None, seed: int = 0,
        progress=None, pool=None) -> Chain:
    """Sample the noise levels; the run length is set by the autocorrelation time (module docstring).

    ``pool``: anything with ``map`` (e.g. a Dask cluster's pool) that evaluates the walkers in parallel."""
    o = options or SamplerOptions()
    walkers, max_steps = o.walkers, o.max_steps
    post = LogPosterior(ml, priors)
    u0 = ml.coords(ml.x_map)
    for i, (pr, lc) in enumerate(zip(post.priors, post.log_coord)):
        lo, hi = pr.bounds()                              # start inside the prior's support
        x = float(ml.x_map[i])
        if np.isfinite(lo):
            x = max(x, lo + 1e-9 * max(1.0, abs(lo)))
        if np.isfinite(hi):
            x = min(x, hi - 1e-9 * max(1.0, abs(hi)))
        u0[i] = math.log(x) if lc else x
    if not np.isfinite(post(u0)):
        raise LogError("the model's noise levels lie outside the prior's support; widen the priors")
    if progress is not None:
        progress.stage("posterior mode", None)
    mode, cov = find_mode(post, u0)
    d = len(mode)
    walkers = walkers or max(2 * d + 2, 12)
    walkers += walkers % 2
    rng = np.random.default_rng(seed)
    Lc = np.linalg.cholesky(cov + 1e-12 * np.eye(d))
    p0 = []
    while len(p0) < walkers:
        u = mode + 0.5 * Lc @ rng.standard_normal(d)
        if np.isfinite(post(u)):
            p0.append(u)
    p0 = np.array(p0)
    sampler = emcee.EnsembleSampler(walkers, d, post,
                                    moves=[(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)], pool=pool)
    sampler.random_state = np.random.RandomState(seed).get_state()
    if progress is not None:
        progress.stage("emcee", max_steps)
    state, steps, tau_old = p0, 0, None
    too_short = True
    while steps < max_steps:
        n = min(o.check_every, max_steps - steps)
        state = sampler.run_mcmc(state, n, progress=False)
        steps += n
        if progress is not None:
            progress.step(n)
        if steps < o.min_steps:
            continue
        tau = sampler.get_autocorr_time(tol=0, quiet=True)
        if not np.all(np.isfinite(tau)):
            continue
        tmax = float(np.max(tau))
        settled = tau_old is not None and np.all(np.abs(tau_old - tau) < 0.05 * tau)
        enough = walkers * (steps - o.burn_taus * tmax) / tmax >= o.target_samples
        tau_old = tau
        if steps >= o.tau_factor * tmax and settled and enough:
            too_short = False
            break
    burn = int(math.ceil(o.burn_taus * np.max(tau_old))) if tau_old is not None else steps // 2
    burn = min(burn, steps // 2)
    tau = sampler.get_autocorr_time(discard=burn, tol=0, quiet=True)
    notes = []
    if too_short or not np.all(np.isfinite(tau)) or steps - burn < 20 * np.max(tau):
        too_short = True
        msg = (f"the chain ({steps} steps) is too short for its autocorrelation time "
               f"(tau up to {np.nanmax(tau):.1f}); run longer (--max-steps) before trusting the tails")
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
        notes.append(msg)
    thin = max(1, int(np.nanmax(tau) / 2)) if np.all(np.isfinite(tau)) else 1
    flat = sampler.get_chain(discard=burn, thin=thin, flat=True)
    natural = np.array([ml.natural(u) for u in flat])
    chain = np.array([[ml.natural(u) for u in row] for row in sampler.get_chain()])
    return Chain(names=list(ml.names), samples=natural, chain=chain, log_prob=sampler.get_log_prob(),
                 walkers=walkers, steps=steps, burn_in=burn, thin=thin, tau=np.asarray(tau, float),
                 acceptance=float(np.mean(sampler.acceptance_fraction)), too_short=too_short,
                 mode=ml.natural(mode), evaluations=post.evaluations + getattr(pool, "items", 0),
                 seconds_per_evaluation=post.seconds / max(post.evaluations, 1),
                 cpu_seconds_per_evaluation=post.cpu_seconds / max(post.evaluations, 1), notes=notes)


def summary(ch: Chain) -> dict:
    """Median, 90 % interval, mean and std of every sampled quantity."""
    out = {}
    for i, n in enumerate(ch.names):
        s = ch.samples[:, i]
        lo, med, hi = np.quantile(s, [0.05, 0.5, 0.95])
        out[n] = {"median": float(med), "ci90": [float(lo), float(hi)], "mean": float(np.mean(s)),
                  "std": float(np.std(s)), "mode": float(ch.mode[i])}
    return out
