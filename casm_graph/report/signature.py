"""Which view of the residuals shows a verdict's trace: the diagnosis report's first panels.

Each catalog effect names its view (:attr:`Effect.signature`): an actuator lag shows in the motion residuals against
the commands' changes over time, a carpet on the floor map, a fading battery in the motion achieved over time, a
moved landmark in its own sightings, false detections in the tails of the sightings' residuals, the others in the
residuals against the covariates they explain (a user's own effect: the strongest). The report opens with the
verdict's view, then its look-alikes', so that the picture a user sees first is the evidence.
"""
from __future__ import annotations

from dataclasses import dataclass

from casm_graph.io.log import LogError
from casm_graph.models.effects.base import get

VIEWS = ("covariates", "correlation", "field", "landmarks", "tails", "speed")
TOP = 3                   # covariate panels in a signature view


@dataclass(frozen=True)
class View:
    """One view: its kind (one of ``VIEWS``), the effects whose trace it shows, and for ``covariates`` the
    (channel, covariate test) pairs to draw, strongest first."""
    kind: str
    effects: tuple[str, ...]
    pairs: tuple = ()


def effect_class(name: str):
    """The catalog class of a verdict or look-alike ``name`` (``name:order`` for a family member), or None."""
    try:
        return get(name)
    except LogError:
        return None


def ranked_pairs(diag, keep=lambda channel, covariate: True, top: int = TOP) -> tuple:
    """The (channel, test) pairs of ``diag.channels`` that ``keep`` accepts, strongest dependence first."""
    pairs = [(ch, c) for ch, r in diag.channels.items() for c in r["covariates"]
             if ch in diag.residuals and keep(ch, c["name"])]
    return tuple(sorted(pairs, key=lambda p: -p[1]["strength"])[:top])


def view_of(diag, name: str) -> View:
    """The view showing the effect ``name``'s trace in ``diag``'s residuals (an effect outside the catalog: the
    strongest dependences)."""
    cls = effect_class(name)
    if cls is None:
        return View("covariates", (name,), ranked_pairs(diag))
    kind = cls.signature if cls.signature in VIEWS else "covariates"
    if kind == "correlation" and not diag.correlation:
        kind = "covariates"
    if kind in ("field", "speed") and not all(ch in diag.residuals for ch in ("forward", "lateral", "turn")):
        kind = "covariates"
    if kind != "covariates":
        return View(kind, (name,))
    explained = set(cls.explains)
    pairs = ranked_pairs(diag, lambda ch, c: (ch, c) in explained)
    return View("covariates", (name,), pairs or ranked_pairs(diag))


def lead(diag) -> list[View]:
    """The views the report opens with: the verdict's, then each look-alike's (a look-alike whose view is one already
    there joins it); for an ``unexplained:<covariate>`` verdict the residuals against that covariate; none for
    ``none``."""
    if diag.verdict.startswith("unexplained:"):
        named = diag.verdict.partition(":")[2]
        return [View("covariates", (diag.verdict,),
                     ranked_pairs(diag, lambda ch, c: c == named) or ranked_pairs(diag))]
    if diag.verdict == "none":
        return []
    names = [diag.verdict] + [e for g in diag.lookalikes for e in g["effects"] if e != diag.verdict]
    views = []
    for name in dict.fromkeys(names):
        v = view_of(diag, name)
        same = next((k for k, w in enumerate(views) if (w.kind, w.pairs) == (v.kind, v.pairs)), None)
        if same is not None:
            views[same] = View(v.kind, views[same].effects + v.effects, v.pairs)
        else:
            views.append(v)
    return views
