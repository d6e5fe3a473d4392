"""The whole loop on a simulated log with a hidden effect: calibrate, diagnose, add, recalibrate, diagnose.

Used by the detection tests, ``benchmarks/detection.py`` and the notebook; it goes through the
same files a user would (the log bundle on disk, RUN/model.json, DIAG/diagnosis.json) and measures
what adding the named effect buys: held-out log-likelihood and the model's error against the truth.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from casm_graph.models.model import Model
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.pipeline import diagnose as diagnose_run
from casm_graph.sim.aibo import SimConfig, simulate, true_reading, write

PAPER_SIM_RMS = np.array([0.02306, 0.01834, 0.086])   # EKFS-EM's simulated errors: vx, vy m/s, w rad/s


def model_error(model: Model, truth: dict) -> dict:
    """Error of a fitted model against a simulated log's truth.

    ``score``: velocity-table RMS per component and sensor-curve RMS (px), in units of the paper's
    simulated errors. ``effect``: the hidden effects' parameters, norm of (fitted - true) over norm
    of true; every catalog effect is neutral at zero, so a model without the effect scores 1.
    ``total`` combines the two (root sum of squares): the whole parameter vector against the truth.
    """
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in model.action_ids])
    rms = np.sqrt(np.mean((model.velocities - tv) ** 2, axis=0))
    d = np.linspace(*truth["sensor_model"]["distance_range"], 200)
    curve = float(np.sqrt(np.mean((model.reading(d) - true_reading(truth, d)) ** 2)))
    score = float(np.sqrt(np.mean((rms / PAPER_SIM_RMS) ** 2) + (curve / 0.35) ** 2))
    effect = effect_error(model.effects or {}, truth.get("effects", {}))
    return {"vx": float(rms[0]), "vy": float(rms[1]), "w": float(rms[2]), "curve": curve, "score": score,
            "effect": effect, "total": float(np.hypot(score, effect))}


def effect_error(fitted: dict, true: dict) -> float:
    """Relative error of the true effects' parameters (0 when no effect is hidden; 1 when none is fitted)."""
    keys = [(name, k) for name in true for k, v in true[name].items() if isinstance(v, (int, float))]
    p = np.array([true[name][k] for name, k in keys], float)
    q = np.array([fitted.get(name, {}).get(k, 0.0) for name, k in keys], float)
    n = np.linalg.norm(p)
    return float(np.linalg.norm(q - p) / n) if n > 0 else 0.0


@dataclass
class Trial:
    """What one hidden-effect trial found; ``score`` is the error in units of the paper's tolerances."""
    effect: str | None
    value: float
    seed: int
    minutes: float
    verdict: str
    candidates: list
    heldout_gain: float | None          # held-out log-likelihood gained by adding the hidden effect (nats)
    error_before: dict
    error_after: dict | None = None
    verdict_after: str | None = None
    fitted: dict = field(default_factory=dict)
    change: dict | None = None          # the second diagnosis against the first (analysis.before_after)
    truth: dict = field(default_factory=dict)
    seconds: float = 0.0
    lookalikes: list = field(default_factory=list)   # the first diagnosis's look-alike groups (their effects)

    def named(self, effect: str | None) -> bool:
        """Whether the first diagnosis named ``effect`` (``None``: none), or a look-alike group holding it."""
        want = effect or "none"
        return self.verdict == want or any(want in g for g in self.lookalikes)

    def to_json(self) -> dict:
        return asdict(self)


def run(effect: str | None, value: float, seed: int, minutes: float, workdir: str | Path,
        after: bool = True, workers: int = 2, effect_class=None, candidates=None) -> Trial:
    """Simulate ``effect=value`` hidden in a ``minutes`` log, diagnose the base model, then add the verdict.

    ``effect_class`` hides a user's effect (not in the catalog) and lets the diagnosis consider it;
    ``candidates`` narrows the effects the diagnosis tries (default: all).
    After the first diagnosis the verdict's effect (when it names one) is added with ``calibrate
    --effect`` and the log diagnosed again.
    """
    t0 = time.perf_counter()
    w = Path(workdir)
    effects = {effect: value} if effect else {}
    extra = (effect_class,) if effect_class is not None else ()
    log, truth = simulate(SimConfig(minutes=minutes, seed=seed, effects=effects, extra_effects=extra))
    write(log, truth, w / "log")
    _, fit = calibrate_run.run(w / "log", w / "run", seed=seed)
    diag = diagnose_run.run(w / "log", w / "run" / "model.json", w / "diag", workers=workers,
                            extra_effects=extra, candidates=candidates)
    cands = [c.to_json() for c in diag.candidates]
    gain = next((c["heldout_nll_drop"] for c in cands if c["effect"] == effect), None)
    trial = Trial(effect, value, seed, minutes, diag.verdict, cands, gain, model_error(fit.model, truth),
                  truth=truth.get("effects", {}), lookalikes=[g["effects"] for g in diag.lookalikes])
    named = diag.verdict if diag.verdict in {c["effect"] for c in cands} else None
    if after and named:
        cls = effect_class if effect_class is not None and named == effect_class.name else diag.to_add()
        _, fit2 = calibrate_run.run(w / "log", w / "run_fixed", effects=(cls,), seed=seed)
        diag2 = diagnose_run.run(w / "log", w / "run_fixed" / "model.json", w / "diag_fixed", workers=workers,
                                 extra_effects=extra, candidates=candidates, before=w / "diag")
        trial.error_after = model_error(fit2.model, truth)
        trial.verdict_after = diag2.verdict
        trial.fitted = fit2.model.effects
        trial.change = diag2.before_after
    trial.seconds = time.perf_counter() - t0
    (w / "trial.json").write_text(json.dumps(trial.to_json(), indent=2, default=float))
    return trial
