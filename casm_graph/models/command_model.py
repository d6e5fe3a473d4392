"""Action model for continuous commands: actual velocity = polynomial of the commanded one.

A wheeled robot commanded ``(v, w)`` moves forward at ``f_v(v)`` and turns at ``f_w(w)`` with no
sideways motion. Each map is a short polynomial in the command divided by a fixed scale (the
largest command magnitude in the log), so every coefficient is a velocity in m/s or rad/s and the
whole model is one parameter vector ``[a_0..a_Dv, b_0..b_Dw]`` that is linear in the basis: the
graph holds it as a single vector variable next to the poses and the sensor polynomial.

With the ``actuator_lag`` effect the velocity follows ``f(command)`` through ``lag_order`` cascaded
first-order lags, each of time constant ``lag / lag_order`` (so ``lag`` is the mean delay whatever the
order), each stage driven by the previous one's mean over the step (order 2: a critically damped drive);
the velocity of a step is the lag's mean over it. The lag acts on the basis, so the model stays linear in its
coefficients; ``velocities(controls)`` without step durations is the steady-state map.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from casm_graph.io.log import LogError
from casm_graph.models.velocity_table import VelocityTable, json_number

KIND = "command_poly"


@njit(cache=True)
def _first_order(x: np.ndarray, a: np.ndarray, g: np.ndarray) -> np.ndarray:
    y = np.empty_like(x)
    y[0] = x[0]
    end = x[0].copy()
    for k in range(1, x.shape[0]):
        y[k] = x[k] + (end - x[k]) * g[k]
        end = a[k] * end + (1.0 - a[k]) * x[k]
    return y


def lagged(x: np.ndarray, dt: np.ndarray, lag: float, order: int = 1) -> np.ndarray:
    """Rows of ``x`` (one per step, held over it) through ``order`` cascaded first-order lags of time constant
    ``lag / order`` (mean delay ``lag``), from rest at x[0]: each row out is the lag's mean over its step, as
    the step's displacement needs (the value at the step's end would lead the motion by half a step per stage)."""
    if lag <= 0:
        return x
    r = np.asarray(dt, float) * order / lag
    a = np.exp(-r)
    g = np.where(r > 1e-9, -np.expm1(-r) / np.maximum(r, 1e-300), 1.0)    # mean of exp(-t / tau) over the step
    y = np.ascontiguousarray(x, dtype=float)
    for _ in range(order):
        y = _first_order(y, a, g)
    return y


@dataclass(frozen=True)
class CommandModel:
    """f_v(v) = sum a_i (v / scale_v)**i, f_w(w) = sum b_i (w / scale_w)**i, lateral velocity 0."""

    kind = KIND
    zero_start = False          # a zero map never moves under EKFS-EM: it starts from the log-only initialiser

    scale: tuple[float, float]            # command scales (v, w)
    v_coef: np.ndarray                    # (Dv+1,)
    w_coef: np.ndarray                    # (Dw+1,)
    v_std: np.ndarray | None = None
    w_std: np.ndarray | None = None
    command_range: tuple = ((0.0, 0.0), (0.0, 0.0))
    lag: float = 0.0                      # s, mean delay of the lag between command and velocity (0: none)
    lag_order: int = 1                    # cascaded first-order stages of that lag (1 or 2)

    @property
    def params(self) -> np.ndarray:
        return np.concatenate([self.v_coef, self.w_coef])

    @property
    def n_v(self) -> int:
        return len(self.v_coef)

    def with_params(self, p: np.ndarray, std: np.ndarray | None = None) -> "CommandModel":
        p = np.asarray(p, float)
        kw = {"v_coef": p[:self.n_v].copy(), "w_coef": p[self.n_v:].copy()}
        if std is not None:
            kw.update(v_std=np.asarray(std[:self.n_v], float), w_std=np.asarray(std[self.n_v:], float))
        return replace(self, **kw)

    def basis(self, controls: np.ndarray, dt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(n, Dv+1) and (n, Dw+1) monomials of the scaled commands; with the steps' ``dt``, through the lag."""
        u = np.asarray(controls, float) / np.asarray(self.scale)
        bv, bw = u[:, 0:1] ** np.arange(self.n_v), u[:, 1:2] ** np.arange(len(self.w_coef))
        if dt is None or self.lag <= 0:
            return bv, bw
        both = lagged(np.hstack([bv, bw]), dt, self.lag, self.lag_order)
        return both[:, :self.n_v], both[:, self.n_v:]

    def lag_memory(self, dt: np.ndarray) -> np.ndarray:
        """(T,) displacement over each step per unit of velocity offset the lag held when the log began (the
        velocity before the first command, unknown: at rest, or settled at another command), as its stages forget
        it: order 1 exp(-t/a), order 2 (1 + t/a) exp(-t/a), a = lag / order, integrated over the step."""
        t1 = np.cumsum(np.asarray(dt, float))
        if self.lag <= 0:
            return np.zeros_like(t1)
        a = self.lag / self.lag_order
        u0, u1 = np.concatenate([[0.0], t1[:-1]]) / a, t1 / a
        if self.lag_order == 2:
            return a * ((2 + u0) * np.exp(-u0) - (2 + u1) * np.exp(-u1))
        return a * (np.exp(-u0) - np.exp(-u1))

    def velocities(self, controls: np.ndarray, dt: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) body-frame (forward, lateral, turn) velocity for each command row (steady state without ``dt``)."""
        bv, bw = self.basis(controls, dt)
        return np.column_stack([bv @ self.v_coef, np.zeros(len(bv)), bw @ self.w_coef])

    def step_velocities(self, log) -> np.ndarray:
        """(T, 3) the map at each step's ``v, w``, through the lag."""
        return self.velocities(log.controls, log.dt)

    def fitted_to_steps(self, log, moved: np.ndarray) -> "CommandModel":
        """The maps' regression on their basis of the steps' displacements ``moved`` (T, 3): forward on the v map,
        turn on the w map (no sideways motion in a command map)."""
        bv, bw = self.basis(log.controls, log.dt)
        dt = np.asarray(log.dt, float)[:, None]
        a = np.linalg.lstsq(bv * dt, moved[:, 0], rcond=None)[0]
        b = np.linalg.lstsq(bw * dt, moved[:, 2], rcond=None)[0]
        return self.with_params(np.concatenate([a, b]))

    def for_log(self, log, source: str = "the model") -> "CommandModel":
        """The map itself, after checking that ``log`` has the ``v, w`` commands it maps."""
        if log.controls is None:
            raise LogError(f"{source} is a command map (continuous commands) and {log.source or 'the log'} runs "
                           f"discrete actions; calibrate this log first")
        if tuple(log.control_names) != ("v", "w"):
            raise LogError(f"commands.csv: the command map needs columns 'v,w' (this log has "
                           f"{','.join(log.control_names)})")
        return self

    def step_table(self, log) -> tuple[np.ndarray, VelocityTable]:
        """(T,) row of each step and the table they index: every step its own row, the map's velocity at that
        step (graph-em's E-step holds them fixed)."""
        return np.arange(log.steps), VelocityTable(np.arange(log.steps), self.step_velocities(log))

    def std_json(self) -> dict:
        """The coefficients' posterior std for a JSON file (the uncertainty run's Laplace section)."""
        def lst(a):
            return None if a is None else np.asarray(a, float).tolist()
        return {"command_std": {"v": lst(self.v_std), "w": lst(self.w_std)}}

    def std_summary(self) -> tuple[str, str] | None:
        """(what, value) of the coefficients' posterior std, None before marginals."""
        if self.v_std is None:
            return None
        return ("command map coefficient std", "v " + ", ".join(f"{x:.2g}" for x in self.v_std)
                + "; w " + ", ".join(f"{x:.2g}" for x in self.w_std))

    def describe(self) -> str:
        return "continuous commands v,w"

    def model_fields(self) -> dict:
        """The :class:`casm_graph.models.model.Model` fields that hold this action model."""
        return {"command": self}

    def to_json(self) -> dict:
        def lst(a):
            return None if a is None else [float(x) for x in a]
        return {"kind": KIND, "commands": ["v", "w"], "lateral": 0.0,
                "scale": {"v": float(self.scale[0]), "w": float(self.scale[1])},
                "coefficients": {"v": lst(self.v_coef), "w": lst(self.w_coef)},
                "std": {"v": lst(self.v_std), "w": lst(self.w_std)},
                "command_range": {"v": [float(x) for x in self.command_range[0]],
                                  "w": [float(x) for x in self.command_range[1]]},
                "lag": float(self.lag), "lag_order": int(self.lag_order)}

    @staticmethod
    def coefficients_in_units(am: dict) -> dict[str, tuple[list, list]]:
        """A command map's coefficients and std per command in the command's own units: model.json's divided by
        ``scale``^i (each log scales by its own largest command, so only these compare across logs)."""
        out = {}
        coefficients = am.get("coefficients")
        if not isinstance(coefficients, dict):
            return out
        std, scale = am.get("std") or {}, am.get("scale") or {}
        for c, coef in coefficients.items():
            s = json_number(scale.get(c, 1.0)) if isinstance(scale, dict) else 1.0
            s = s if np.isfinite(s) and s > 0 else 1.0
            sd = (std.get(c) if isinstance(std, dict) else None) or [None] * len(coef)
            out[c] = ([json_number(v) / s ** i for i, v in enumerate(coef)],
                      [(json_number(sd[i]) if i < len(sd) else np.nan) / s ** i for i in range(len(coef))])
        return out

    @staticmethod
    def figures(am: dict) -> list[tuple[str, str, float, float]]:
        """(name, family, value, std) of every figure of a command map's model.json entry ``am``: its coefficients
        in the command's own units."""
        return [(f"{c} coef {i}", "command_map", v, e) for c, (coef, sd) in CommandModel.coefficients_in_units(am).items()
                for i, (v, e) in enumerate(zip(coef, sd))]

    @staticmethod
    def brief(am: dict) -> dict:
        """A command map's model.json entry in brief, for a fleet's table: its coefficients in the command's units."""
        return {f"{c}_coef_{i}": v for c, (coef, _) in CommandModel.coefficients_in_units(am).items()
                for i, v in enumerate(coef)}

    @classmethod
    def from_json(cls, am: dict) -> "CommandModel":
        std = am.get("std") or {}
        rng = am.get("command_range") or {}
        return cls(scale=(float(am["scale"]["v"]), float(am["scale"]["w"])),
                   v_coef=np.array(am["coefficients"]["v"], float),
                   w_coef=np.array(am["coefficients"]["w"], float),
                   v_std=None if std.get("v") is None else np.array(std["v"], float),
                   w_std=None if std.get("w") is None else np.array(std["w"], float),
                   command_range=(tuple(rng.get("v", (0.0, 0.0))), tuple(rng.get("w", (0.0, 0.0)))),
                   lag=float(am.get("lag", 0.0)), lag_order=int(am.get("lag_order", 1)))


def for_commands(controls: np.ndarray, v_degree: int = 2, w_degree: int = 1,
                 gain: float = 0.0) -> CommandModel:
    """A model sized for ``controls``: every map ``gain`` times the identity (0: the paper's zero start)."""
    scale = np.max(np.abs(controls), axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    v, w = np.zeros(v_degree + 1), np.zeros(w_degree + 1)
    v[1], w[1] = gain * scale[0], gain * scale[1]
    rng = ((float(controls[:, 0].min()), float(controls[:, 0].max())),
           (float(controls[:, 1].min()), float(controls[:, 1].max())))
    return CommandModel(scale=(float(scale[0]), float(scale[1])), v_coef=v, w_coef=w, command_range=rng)
