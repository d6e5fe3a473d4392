"""Action model for discrete actions: the paper's velocity table, one body-frame (vx, vy, w) per action id.

It answers what :class:`casm_graph.models.command_model.CommandModel` answers for continuous commands (its
parameters as one vector, each step's velocity, the least-squares fit to given displacements, its JSON), so that
code above the action model never asks which kind a log has.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace

import numpy as np

from casm_graph.io.log import LogError
from casm_graph.models.validate import Where


AXES = ("vx", "vy", "w")


def json_number(x) -> float:
    """A model.json figure as a float, NaN where it is missing, not a number or not finite (a fleet's files vary)."""
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else math.nan

KIND = "table"
_ID = re.compile(r"[+-]?[0-9]+", re.ASCII)


def action_ids(w: Where, keys, where: str) -> list[tuple[int, str]]:
    """(id, key) of each key of a table's entry, sorted by id; a key that is no integer, or one named twice, fails."""
    out, seen = [], set()
    for k in keys:
        if not _ID.fullmatch(k) or abs(int(k)) > 2 ** 63 - 1:
            w.fail(where, f"has key {k[:40]!r}, which is not an integer action id")
        a = int(k)
        if a in seen:
            w.fail(where, f"names action {a} twice")
        seen.add(a)
        out.append((a, k))
    return sorted(out)


@dataclass(frozen=True)
class VelocityTable:
    """Velocity ``velocities[i]`` (m/s, m/s, rad/s) for action ``action_ids[i]``; ``velocity_std`` its posterior std."""

    action_ids: np.ndarray
    velocities: np.ndarray
    velocity_std: np.ndarray | None = None

    kind = KIND
    zero_start = True           # EKFS-EM may start from the paper's zero table: the filter's sightings move it

    @property
    def params(self) -> np.ndarray:
        return np.asarray(self.velocities, float).ravel()

    def with_params(self, p: np.ndarray, std: np.ndarray | None = None) -> "VelocityTable":
        kw = {} if std is None else {"velocity_std": np.asarray(std, float).reshape(-1, 3)}
        return replace(self, velocities=np.asarray(p, float).reshape(-1, 3), **kw)

    def scaled(self, s: float) -> "VelocityTable":
        """The table on a map ``s`` times as large: the forward and sideways velocities (and their std) times ``s``."""
        f = np.array([s, s, 1.0])
        return replace(self, velocities=np.asarray(self.velocities, float) * f,
                       velocity_std=None if self.velocity_std is None else np.asarray(self.velocity_std, float) * f)

    def rows_of(self, action: np.ndarray) -> np.ndarray:
        """(n,) the table's row of each action id in ``action``."""
        return np.searchsorted(self.action_ids, action)

    def velocity_of(self, action: np.ndarray) -> np.ndarray:
        """(n, 3) the velocity of each action id in ``action``."""
        return self.velocities[self.rows_of(action)]

    def step_velocities(self, log) -> np.ndarray:
        """(T, 3) the row of each step's action."""
        return self.velocity_of(log.action)

    def step_displacements(self, log) -> np.ndarray:
        """(T, 3) each step's displacement: its row times the step's time (the paper's step, along its start
        heading)."""
        return self.step_velocities(log) * np.asarray(log.dt, float)[:, None]

    def fitted_to_steps(self, log, moved: np.ndarray) -> "VelocityTable":
        """Each action's mean velocity over the steps that ran it (displacements ``moved``, (T, 3)); actions never
        run keep theirs."""
        act = self.rows_of(log.action)
        total, time = np.zeros_like(self.velocities), np.zeros(len(self.action_ids))
        np.add.at(total, act, moved)
        np.add.at(time, act, log.dt)
        return replace(self, velocities=np.where(time[:, None] > 0, total / np.maximum(time, 1e-12)[:, None],
                                                 self.velocities))

    def for_log(self, log, source: str = "the model") -> "VelocityTable":
        """The table indexed like ``log``'s actions (no std: it is the log's to give); a clear error when the log
        has continuous commands or runs an action the table has no velocity for."""
        if log.action is None:
            raise LogError(f"{source} has no command map (action_model.kind 'command_poly') for "
                           f"{log.source or 'the log'}'s continuous commands; calibrate this log first")
        missing = sorted(set(log.action_ids.tolist()) - set(np.asarray(self.action_ids).tolist()))
        if missing:
            raise LogError(f"{source} has no velocity for action(s) {missing[:10]} that the log runs")
        return VelocityTable(log.action_ids, self.velocity_of(log.action_ids))

    def step_table(self, log) -> tuple[np.ndarray, "VelocityTable"]:
        """(T,) row of each step and the table they index: the table itself (graph-em's E-step sees every log as
        one)."""
        return self.rows_of(log.action), self

    def std_json(self) -> dict:
        """The parameters' posterior std for a JSON file (the uncertainty run's Laplace section)."""
        std = self.velocity_std if self.velocity_std is not None else np.full_like(self.velocities, np.nan)
        return {"velocity_std": {str(int(a)): s.tolist() for a, s in zip(self.action_ids, std)}}

    def std_summary(self) -> tuple[str, str] | None:
        """(what, value) of the parameters' posterior std in units, None before marginals."""
        if self.velocity_std is None or not np.isfinite(self.velocity_std).any():
            return None
        med = np.nanmedian(self.velocity_std, axis=0)
        return ("action table std (median over actions)",
                f"vx {1000 * med[0]:.1f} mm/s, vy {1000 * med[1]:.1f} mm/s, w {med[2]:.4f} rad/s")

    def describe(self) -> str:
        return f"action table, {len(self.action_ids)} actions"

    def model_fields(self) -> dict:
        """The :class:`casm_graph.models.model.Model` fields that hold this action model."""
        return {"action_ids": self.action_ids, "velocities": self.velocities, "velocity_std": self.velocity_std,
                "command": None}

    @staticmethod
    def figures(am: dict) -> list[tuple[str, str, float, float]]:
        """(name, family, value, std) of every figure of a table's model.json entry ``am``, read as a fleet's files
        come (missing std NaN): each action's vx, vy, w."""
        vel, std = am.get("velocities", {}) or {}, am.get("std", {}) or {}
        out = []
        for a in sorted(vel, key=lambda s: int(s)):
            sd = std.get(a) or [None] * 3
            out += [(f"action {a} {ax}", "velocities", json_number(vel[a][i]),
                     json_number(sd[i] if i < len(sd) else None)) for i, ax in enumerate(AXES)]
        return out

    @staticmethod
    def brief(am: dict) -> dict:
        """A table's model.json entry in brief, for a fleet's table: its size and mean absolute velocity per axis."""
        vel = np.array([[json_number(v) for v in vs] for vs in (am.get("velocities") or {}).values()],
                       float).reshape(-1, 3)
        mean = np.nanmean(np.abs(vel), axis=0) if len(vel) else np.full(3, np.nan)
        return {"actions": len(vel), **{f"mean_abs_{ax}": float(v) for ax, v in zip(AXES, mean)}}

    @classmethod
    def read(cls, w: Where, am: dict) -> "VelocityTable":
        """The table of model.json's ``action_model`` entry ``am``, each field checked (``w`` names the file)."""
        velocities = w.obj(am.get("velocities"), "action_model.velocities")
        pairs = action_ids(w, velocities.keys(), "action_model.velocities")
        ids = np.array([a for a, _ in pairs], np.int64)
        vel = np.array([w.vec(velocities[k], f"action_model.velocities.{k}", n=3) for _, k in pairs],
                       float).reshape(len(ids), 3)
        std = am.get("std")
        vstd = None
        if std:
            std = w.obj(std, "action_model.std")
            vstd = np.array([w.vec(std[k], f"action_model.std.{k}", n=3, nullable=True, nonneg=True)
                             if std.get(k) is not None else np.full(3, np.nan) for _, k in pairs],
                            float).reshape(len(ids), 3)
        return cls(ids, vel, vstd)

    def to_json(self) -> dict:
        ids = [str(int(a)) for a in self.action_ids]
        std = self.velocity_std if self.velocity_std is not None else np.full_like(self.velocities, np.nan)
        return {"kind": KIND, "velocities": {a: v.tolist() for a, v in zip(ids, self.velocities)},
                "std": {a: s.tolist() for a, s in zip(ids, std)}}
