"""The simulators by protocol name, for the command line and the Python API.

``aibo``: the EKFS-EM paper's field (an action table, catalog effects by name); ``floor``: a wheeled
robot with ``v,w`` commands on a floor whose motion noise differs by region; ``scasm-1d``: SCASM's walk
to and from one beacon. Each returns the log and its truth (the true models, as truth_model.json).
``sensor`` ("range", "bearing" or "both") chooses the measured cells on ``aibo`` and ``floor``.
"""
from __future__ import annotations

import math
from dataclasses import fields as dataclass_fields
from pathlib import Path

from casm_graph.io.log import Log, LogError
from casm_graph.io.log import write as write_bundle
from casm_graph.sim import aibo
from casm_graph.sim import floor as simulate_floor
from casm_graph.sim import walk_1d as simulate_1d

CONFIGS = {"aibo": aibo.SimConfig, "floor": simulate_floor.FloorConfig, "scasm-1d": simulate_1d.Sim1DConfig}
RUN = {"aibo": aibo.simulate, "floor": simulate_floor.simulate, "scasm-1d": simulate_1d.simulate}
OWN_FLAGS = {"minutes": "--minutes", "seed": "--seed", "effects": "--effect", "sensor": "--sensor"}


def simulate(protocol: str = "aibo", minutes: float = 15.0, seed: int = 0, effects: dict | None = None,
             **options) -> tuple[Log, dict]:
    """A simulated log of ``protocol`` and its truth; ``options`` are fields of that protocol's config."""
    if protocol not in CONFIGS:
        raise LogError(f"unknown protocol {protocol!r} (known: {', '.join(CONFIGS)})")
    if effects and protocol != "aibo":
        raise LogError(f"effects by name are only available with the aibo protocol (got {protocol}); the floor "
                       f"simulator takes lag and lens_k options (--option lag=0.3)")
    if protocol == "scasm-1d" and options.get("sensor", "both") != "both":
        raise LogError(f"sensor {options['sensor']!r}: the scasm-1d walk has no sensor choice (the 1-D methods "
                       "need the beacon height, its bearing is always straight ahead); use --protocol floor or aibo")
    if protocol == "scasm-1d":
        options.pop("sensor", None)
    fields = set(CONFIGS[protocol].__dataclass_fields__)
    unknown = sorted(set(options) - fields)
    if unknown:
        raise LogError(f"{protocol} simulator: unknown option(s) {unknown} (known: {', '.join(sorted(fields))})")
    if protocol == "aibo":
        options["effects"] = dict(effects or {})
    return RUN[protocol](CONFIGS[protocol](minutes=minutes, seed=seed, **options))


def write_log(log: Log, directory, truth: dict | None = None) -> Path:
    """Write ``log`` as a bundle in ``directory`` (with truth_model.json when ``truth`` is given)."""
    return aibo.write(log, truth, directory) if truth is not None else write_bundle(log, directory)


def parse_options(protocol: str, items: list[str], taken: tuple[str, ...] = ()) -> dict:
    """``NAME=VALUE`` texts as fields of ``protocol``'s config, typed as each field is declared.

    A tuple field takes comma-separated numbers; ``taken`` names fields a dedicated flag already sets."""
    if protocol not in CONFIGS:
        raise LogError(f"unknown protocol {protocol!r} (known: {', '.join(CONFIGS)})")
    settable = {f.name: str(f.type) for f in dataclass_fields(CONFIGS[protocol])
                if f.name not in OWN_FLAGS and f.name not in taken and _kind(str(f.type)) is not None}
    out = {}
    for item in items:
        name, sep, raw = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise LogError(f"--option {item!r}: expected NAME=VALUE")
        if name in OWN_FLAGS or name in taken:
            raise LogError(f"--option {name}: set it with {OWN_FLAGS.get(name, '--' + name.replace('_', '-'))}")
        if name not in settable:
            raise LogError(f"--option {name}: not an option of the {protocol} simulator "
                           f"(known: {', '.join(sorted(settable))})")
        out[name] = _typed(name, raw.strip(), settable[name])
    return out


def _kind(annotation: str):
    """(type, 0) for a scalar field, (element type, length or None) for a tuple one; None if not settable."""
    simple = {"int": int, "float": float, "str": str}
    if annotation in simple:
        return simple[annotation], 0
    if annotation.startswith("tuple[") and annotation.endswith("]"):
        parts = [p.strip() for p in annotation[6:-1].split(",")]
        if parts and parts[0] in ("int", "float") and set(parts[1:]) <= {parts[0], "..."}:
            return simple[parts[0]], None if "..." in parts else len(parts)
    return None


def _typed(name: str, raw: str, annotation: str):
    """``raw`` converted to the declared type; one clear line when it does not fit."""
    kind, count = _kind(annotation)
    if kind is str:
        return raw
    if count == 0:
        return _number(name, raw, kind)
    values = tuple(_number(name, p.strip(), kind) for p in raw.split(",") if p.strip())
    if count is not None and len(values) != count:
        raise LogError(f"--option {name}={raw}: expected {count} comma-separated numbers")
    return values


def _number(name: str, raw: str, kind: type):
    """One int or float from text, finite."""
    try:
        value = kind(raw)
    except ValueError:
        raise LogError(f"--option {name}={raw}: the value must be "
                       f"{'a whole number' if kind is int else 'a number'}") from None
    if not math.isfinite(value):
        raise LogError(f"--option {name}={raw}: the value must be finite")
    return value
