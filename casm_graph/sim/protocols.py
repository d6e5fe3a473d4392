"""The simulators by protocol name, for the command line and the Python API.

``aibo``: the EKFS-EM paper's field (an action table, catalog effects by name); ``floor``: a wheeled
robot with ``v,w`` commands on a floor whose motion noise differs by region; ``scasm-1d``: SCASM's walk
to and from one beacon. Each returns the log and its truth (the true models, as truth_model.json).
"""
from __future__ import annotations

from pathlib import Path

from casm_graph.io.log import Log, LogError
from casm_graph.io.log import write as write_bundle
from casm_graph.sim import aibo
from casm_graph.sim import floor as simulate_floor
from casm_graph.sim import walk_1d as simulate_1d

CONFIGS = {"aibo": aibo.SimConfig, "floor": simulate_floor.FloorConfig, "scasm-1d": simulate_1d.Sim1DConfig}
RUN = {"aibo": aibo.simulate, "floor": simulate_floor.simulate, "scasm-1d": simulate_1d.simulate}


def simulate(protocol: str = "aibo", minutes: float = 15.0, seed: int = 0, effects: dict | None = None,
             **options) -> tuple[Log, dict]:
    """A simulated log of ``protocol`` and its truth; ``options`` are fields of that protocol's config."""
    if protocol not in CONFIGS:
        raise LogError(f"unknown protocol {protocol!r} (known: {', '.join(CONFIGS)})")
    if effects and protocol != "aibo":
        raise LogError(f"effects by name are only available with the aibo protocol (got {protocol}); the floor "
                       f"simulator takes lag= and lens_k= options")
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
