"""The effect catalog (INTERFACE section 6): one module per physical effect, a registry by name.

Write your own by subclassing :class:`Effect` and decorating it with :func:`register`; see the
README section "Add your own effect".
"""
from casm_graph.models.effects import (
    actuator_lag,  # noqa: F401
    battery_fade,  # noqa: F401
    camera_latency,  # noqa: F401
    false_detections,  # noqa: F401
    landmark_offset,  # noqa: F401
    lens_distortion,  # noqa: F401
    proposal,
    range_dependent_noise,  # noqa: F401
    regional_motion_noise,  # noqa: F401
    surface_friction,  # noqa: F401
)
from casm_graph.models.effects.base import REGISTRY, Effect, get, register, spec, unphysical

__all__ = ["REGISTRY", "Effect", "get", "register", "spec", "unphysical", "catalog", "of_model", "unresolved"]


def of_model(effects: dict, own=()) -> list[type[Effect]]:
    """The classes of a model's ``effects`` entries: ``own`` (user classes) by name, the catalog's, and a
    proposal rebuilt from its stored terms (:mod:`casm_graph.models.effects.proposal`)."""
    mine = {cls.name: cls for cls in own}
    out = [mine[name] if name in mine else proposal.proposal_effect(entry) if name == proposal.NAME else get(name)
           for name, entry in effects.items()]
    return [cls.of_order(int(entry["order"])) if cls.orders and entry.get("order") is not None else cls
            for cls, entry in zip(out, effects.values())]


def unresolved(effects: dict, own=()) -> list[str]:
    """Names in a model's ``effects`` that :func:`of_model` cannot resolve: neither ``own``, the catalog's
    nor a proposal."""
    mine = {cls.name for cls in own}
    return [name for name in effects if name not in mine and name not in REGISTRY and name != proposal.NAME]


def catalog() -> list[dict]:
    """Name, channel, parameters (of the default order) and physics of every registered effect; a family's
    orders."""
    out = []
    for name in sorted(REGISTRY):
        e = REGISTRY[name]()
        out.append({"name": name, "channel": e.channel, "parameters": list(e.params),
                    "physics": e.physics, **({"orders": list(e.orders), "order": e.order} if e.orders else {})})
    return out
