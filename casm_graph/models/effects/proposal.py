"""proposal: a motion effect written as an equation from a library of terms, not a catalog physics.

The diagnosis proposes one (:mod:`casm_graph.analysis.proposal`) when no catalog effect explains the
motion residuals' structure: ``forward velocity += 0.03 v_forward*cos(heading) - 0.02 y``. Each
parameter is a term's coefficient and is named ``"<axis>: <term>"``, so model.json alone says what
the effect computes and :func:`proposal_effect` rebuilds it from a model.json entry. Terms are the library's features of the
step (heading, position, time, speed, the velocities, a slow oscillation in time), alone or times the axis's
own velocity, and the turn rate over the speed (``w/speed``: a car's firmware that steers for the
commanded speed turns at w v_true / v, so an offset in the speed map leaves a term in w/v).
"""
from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np

from casm_graph.io.log import LogError
from casm_graph.models.effects.base import Effect

NAME = "proposal"
AXES = ("forward", "lateral", "turn")
OWN = {"forward": "v_forward", "lateral": "v_lateral", "turn": "w"}   # each axis's own velocity (model's table or map)
_CLASSES: dict[str, type[Effect]] = {}     # built proposals by class name, so pickle finds the very class


BASE_TERMS = ("cos(heading)", "sin(heading)", "x", "y", "t", "speed", "v_forward", "v_lateral", "w", "|w|")
OVER_SPEED = {"turn": "w/speed"}   # the own velocity over the speed, a term of these axes only (a forward speed
#                                    over the speed is its sign: a creep, not a ratio)
SPEED_FLOOR = 0.05         # m/s: 1/speed is taken at no less than this (a robot turning in place has no speed)
PERIODIC = re.compile(r"^(sin|cos)\(2pi t/([0-9]+(?:\.[0-9]+)?)s\)$")   # a slow oscillation in time, period in s


def periodic_terms(period: float) -> tuple[str, str]:
    """The two terms of an oscillation of ``period`` seconds."""
    return f"sin(2pi t/{period:.0f}s)", f"cos(2pi t/{period:.0f}s)"


def _base(name: str, pose: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """One base feature: heading, position (m), time (min), speed and velocities (m/s, rad/s), an oscillation."""
    fixed = {"cos(heading)": lambda: np.cos(pose[:, 2]), "sin(heading)": lambda: np.sin(pose[:, 2]),
             "x": lambda: pose[:, 0], "y": lambda: pose[:, 1], "t": lambda: t / 60.0,
             "speed": lambda: np.hypot(v[:, 0], v[:, 1]), "v_forward": lambda: v[:, 0], "v_lateral": lambda: v[:, 1],
             "w": lambda: v[:, 2], "|w|": lambda: np.abs(v[:, 2]),
             "1/speed": lambda: 1.0 / np.maximum(np.hypot(v[:, 0], v[:, 1]), SPEED_FLOOR)}
    if name in fixed:
        return fixed[name]()
    m = PERIODIC.match(name)
    if m:
        return getattr(np, m.group(1))(2 * np.pi * t / float(m.group(2)))
    return None


def with_own(axis: str, base) -> tuple[str, ...]:
    """The terms of ``axis`` from base features: each alone (not the axis's own velocity: that is the model's
    gain) and times the axis's own velocity (not times a velocity)."""
    own = OWN[axis]
    return tuple(b for b in base if b != own) + tuple(f"{own}*{b}" for b in base if b not in OWN.values())


def library(axis: str, periods=()) -> tuple[str, ...]:
    """The terms a proposal on ``axis`` may use (:func:`with_own` of the base features, and :data:`OVER_SPEED`'s);
    ``periods`` (s) add oscillations in time."""
    return (with_own(axis, BASE_TERMS + tuple(term for p in periods for term in periodic_terms(p)))
            + ((OVER_SPEED[axis],) if axis in OVER_SPEED else ()))


def split_term(axis: str, term: str) -> tuple[bool, str]:
    """(times the own velocity?, base feature) of a term of ``axis``."""
    own = OWN[axis]
    if term == OVER_SPEED.get(axis):
        return True, "1/speed"
    return (True, term[len(own) + 1:]) if term.startswith(own + "*") else (False, term)


def features(axis: str, terms, ctx: dict, v: np.ndarray) -> np.ndarray:
    """(n, len(terms)) the ``terms`` of ``axis`` on steps with context ``ctx`` (``pose``, ``t``) and velocity ``v``."""
    u = v[:, AXES.index(axis)]
    cols = []
    for term in terms:
        times_own, b = split_term(axis, term)
        col = _base(b, ctx["pose"], ctx["t"], v)
        if col is None:
            raise LogError(f"proposal term {term!r} on {axis}: not in the library ({', '.join(library(axis))}, "
                           "sin/cos(2pi t/<period>s))")
        cols.append(u * col if times_own else col)
    return np.column_stack(cols) if cols else np.zeros((len(v), 0))


def parse(names) -> list[tuple[str, str]]:
    """(axis, term) of each parameter name ``"<axis>: <term>"``."""
    out = []
    for name in names:
        axis, sep, term = str(name).partition(": ")
        ok = sep and axis in AXES
        if ok:
            _, b = split_term(axis, term)
            ok = (b in BASE_TERMS or PERIODIC.match(b) or term == OVER_SPEED.get(axis)) and b != OWN[axis]
        if not ok:
            raise LogError(f"proposal parameter {name!r}: expected '<axis>: <term>' with axis one of "
                           f"{', '.join(AXES)} and a library term")
        out.append((axis, term))
    return out


def equation(coefficients: dict) -> list[str]:
    """One readable line per axis: ``forward velocity += 0.03 v_forward*cos(heading) - 0.02 y``."""
    lines = []
    terms = parse(coefficients)
    for axis in AXES:
        parts = [(c, term) for (a, term), c in zip(terms, coefficients.values()) if a == axis]
        if not parts:
            continue
        text = " ".join(f"{'-' if c < 0 else '+'} {abs(c):.3g} {term}" for c, term in parts)
        unit = "rad/s" if axis == "turn" else "m/s"
        lines.append(f"{axis} velocity ({unit}) += {text.removeprefix('+ ')}")
    return lines


def _class_name(coefficients: dict) -> str:
    """A class name that spells the proposal (base32 of its JSON), so worker processes can rebuild it."""
    code = base64.b32encode(json.dumps(coefficients).encode()).decode().rstrip("=")
    return f"Proposal_{code}"


def __getattr__(name: str):
    """Unpickling a proposal class in another process: rebuild it from its name."""
    if name.startswith("Proposal_"):
        code = name[len("Proposal_"):]
        return proposal_effect(json.loads(base64.b32decode(code + "=" * (-len(code) % 8))))
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def proposal_effect(coefficients: dict) -> type[Effect]:
    """The effect class of a proposal: ``coefficients`` maps ``"<axis>: <term>"`` to its starting value."""
    coefficients = {str(k): float(v) for k, v in coefficients.items()}
    cls_name = _class_name(coefficients)
    if cls_name in _CLASSES:
        return _CLASSES[cls_name]
    names = tuple(coefficients)
    terms = parse(names)
    start = tuple(float(c) for c in coefficients.values())
    by_axis = {a: [i for i, (ax, _) in enumerate(terms) if ax == a] for a in AXES}

    class Proposal(Effect):
        __doc__ = "A proposed motion effect: " + "; ".join(equation(coefficients))
        name = NAME
        channel = "motion"
        params = names
        scale = tuple(max(abs(s), 1e-3) for s in start)
        explains = tuple((a, "proposal") for a in AXES if by_axis[a])
        map_bound = any(re.search(r"\b[xy]\b|heading", term) for _, term in terms)
        physics = ("Proposed by the diagnosis from the motion residuals (a sparse regression over a library of "
                   "terms, no catalog physics): " + "; ".join(equation(coefficients)) + ".")

        def velocity(self, theta, v, ctx):
            out = np.array(v, float)
            for k, axis in enumerate(AXES):
                idx = by_axis[axis]
                if idx:
                    out[:, k] += features(axis, [terms[i][1] for i in idx], ctx, v) @ np.asarray(theta)[idx]
            return out

    Proposal.start = start
    Proposal.__name__ = Proposal.__qualname__ = cls_name
    Proposal.__module__ = __name__
    _CLASSES[cls_name] = Proposal
    return Proposal


def from_diagnosis(path) -> type[Effect]:
    """The proposal of a diagnosis (its directory or diagnosis.json), for ``calibrate --effect proposal``."""
    f = Path(path)
    f = f / "diagnosis.json" if f.is_dir() else f
    try:
        data = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        raise LogError(f"--proposal {path}: cannot read a diagnosis.json there ({e})") from None
    terms = data.get("proposal", {}).get("terms") if isinstance(data, dict) else None
    if not terms:
        raise LogError(f"--proposal {f}: this diagnosis proposed no effect (a proposal comes with an "
                       f"'unexplained:<covariate>' verdict whose motion residuals a library term explains)")
    return proposal_effect(terms)
