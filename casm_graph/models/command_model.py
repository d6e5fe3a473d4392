"""Action model for continuous commands: actual velocity = polynomial of the commanded one.

A wheeled robot commanded ``(v, w)`` moves forward at ``f_v(v)`` and turns at ``f_w(w)`` with no
sideways motion; an omnidirectional one commanded ``(vx, vy, w)`` also moves sideways at ``f_y(vy)``.
Each map is a short polynomial in its command divided by a fixed scale (the largest command magnitude
in the log), so every coefficient is a velocity in m/s or rad/s and the whole model is one parameter
vector ``[a_0..a_Dv, c_0..c_Dy, b_0..b_Dw]`` (no ``c`` without a sideways command) that is linear in the
basis: the graph holds it as a single vector variable next to the poses and the sensor polynomial.

With ``cross`` (wheeled ``v, w`` commands only) the turn map is also linear in the forward command: a
differential drive whose wheels differ in size turns while commanded straight (turn rate += b_x v / scale_v,
UMBmark's wheel-diameter error). The cross coefficient is the turn map's last entry, after its power series.
(The same wheels' speed term in ``w``, a quarter of the track times the gain difference, is second order; on
MRCLAM robot 4 it ran to -0.16 and took the speed map 70 % of its range from Vicon's.)

A step moves the robot along its heading at the step's middle (``step_heading`` "middle", the default: the chord
of the arc a command held over the step drives) or at its start ("start", the paper's step, which model.json
files written before the choice used). The start leaves a sideways error of v w dt / 2 that a fast robot on slow
commands shows (a car at 1-2 m/s on 10-20 Hz commands: lateral residuals following the turn rate).

With the ``actuator_lag`` effect the velocity follows ``f(command)`` through ``lag_order`` cascaded
first-order lags, each of time constant ``lag / lag_order`` (so ``lag`` is the mean delay whatever the
order), each stage driven by the previous one's mean over the step (order 2: a critically damped drive);
the velocity of a step is the lag's mean over it (the formulas are the effect's own,
:mod:`casm_graph.models.effects.actuator_lag`). The lag acts on the basis, so the model stays linear in its
coefficients; ``velocities(controls)`` without step durations is the steady-state map.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

import factors.command
from casm_graph.io.log import LogError
from casm_graph.models.effects.actuator_lag import lagged, memory
from casm_graph.models.validate import MAX_POLY, Where, one_line
from casm_graph.models.velocity_table import VelocityTable, json_number

KIND = "command_poly"
COMMANDS = (("v", "w"), ("vx", "vy", "w"))      # the command columns a map can read: wheeled, omnidirectional
STEP_HEADINGS = ("start", "middle")             # the heading a step moves along (CommandModel.step_heading)
AXIS_WORDS = (("speed", "m/s"), ("sideways speed", "m/s"), ("turn rate", "rad/s"))   # what a map gives, by body axis


def map_name(axis: int) -> str:
    """The short name of the map onto body axis ``axis`` in reports: speed map, sideways map, turn map."""
    return AXIS_WORDS[axis][0].split()[0] + " map"


@dataclass(frozen=True)
class CommandModel:
    """f_v(v) = sum a_i (v / scale_v)**i, f_w(w) = sum b_i (w / scale_w)**i; lateral velocity 0 for ``v, w``
    commands, f_y(vy) = sum c_i (vy / scale_vy)**i for ``vx, vy, w``."""

    kind = KIND
    zero_start = False          # a zero map never moves under EKFS-EM: it starts from the log-only initialiser

    scale: tuple[float, ...]              # command scales, one per command column
    v_coef: np.ndarray                    # (Dv+1,) forward map
    w_coef: np.ndarray                    # (Dw+1,) turn map
    v_std: np.ndarray | None = None
    w_std: np.ndarray | None = None
    command_range: tuple = ((0.0, 0.0), (0.0, 0.0))
    lag: float = 0.0                      # s, mean delay of the lag between command and velocity (0: none)
    lag_order: int = 1                    # cascaded first-order stages of that lag (1 or 2)
    commands: tuple[str, ...] = ("v", "w")   # the command columns: ``v, w`` or ``vx, vy, w``
    y_coef: np.ndarray = field(default_factory=lambda: np.zeros(0))   # (Dy+1,) sideways map (``vy`` commands only)
    y_std: np.ndarray | None = None
    cross: bool = False                   # the turn map of ``v, w`` also linear in ``v`` (its last coefficient)
    step_heading: str = "middle"          # each step moves along its heading at the "start" or the middle

    @property
    def lead(self) -> float:
        """The share of a step's turn made before it moves (:mod:`factors.command`)."""
        return 0.5 if self.step_heading == "middle" else 0.0

    @property
    def params(self) -> np.ndarray:
        return np.concatenate([self.v_coef, self.y_coef, self.w_coef])

    @property
    def n_v(self) -> int:
        return len(self.v_coef)

    @property
    def sizes(self) -> tuple[int, int, int]:
        """Coefficients of the forward, sideways (0 without ``vy``) and turn maps, in the parameter vector's order."""
        return len(self.v_coef), len(self.y_coef), len(self.w_coef)

    @property
    def maps(self) -> list[tuple[str, int, int, slice]]:
        """(command, its column in the controls, the body axis it drives, its slice of ``params``) of each map."""
        nv, ny, nw = self.sizes
        out = [(self.commands[0], 0, 0, slice(0, nv))]
        if len(self.commands) == 3:
            out.append((self.commands[1], 1, 1, slice(nv, nv + ny)))
        out.append((self.commands[-1], len(self.commands) - 1, 2, slice(nv + ny, nv + ny + nw)))
        return out

    def _map(self, command: str) -> tuple[np.ndarray, np.ndarray | None, int]:
        """(whole coefficient vector, its std or None, how many of them are the power series) of a map."""
        axis = next(a for c, _, a, _ in self.maps if c == command)
        coef, std = [(self.v_coef, self.v_std), (self.y_coef, self.y_std), (self.w_coef, self.w_std)][axis]
        return coef, std, len(coef) - (self.cross and axis == 2)

    def coefficients(self, command: str) -> tuple[np.ndarray, np.ndarray | None]:
        """(power-series coefficients, their posterior std or None) of the map of ``command``."""
        coef, std, n = self._map(command)
        return coef[:n], None if std is None else std[:n]

    def cross_coefficient(self, command: str) -> tuple[float, float | None] | None:
        """(coefficient on v / its scale, std or None) of the map of ``command``; None where it has none (without
        ``cross``, and every map but the turn map)."""
        coef, std, n = self._map(command)
        if n == len(coef):
            return None
        return float(coef[n]), None if std is None else float(std[n])

    def with_cross(self) -> "CommandModel":
        """This map with the turn map's term in ``v`` added at 0 (itself when it has it, or has no ``v, w``)."""
        if self.cross or tuple(self.commands) != COMMANDS[0]:
            return self
        return replace(self, w_coef=np.append(self.w_coef, 0.0), w_std=None, v_std=None, cross=True)

    def scaled(self, s: float) -> "CommandModel":
        """The maps on a map ``s`` times as large: the forward and sideways maps (and their std) times ``s``."""
        def times(a):
            return None if a is None else np.asarray(a, float) * s
        return replace(self, v_coef=times(self.v_coef), v_std=times(self.v_std), y_coef=times(self.y_coef),
                       y_std=times(self.y_std))

    def same_form(self, controls: np.ndarray, gain: float = 1.0) -> "CommandModel":
        """A map of this one's degrees and cross terms sized for ``controls``, ``gain`` times the identity."""
        nv, ny, nw = self.sizes
        return replace(for_commands(controls, nv - 1, nw - 1 - self.cross, gain=gain, y_degree=ny - 1, cross=self.cross),
                       lag=self.lag, lag_order=self.lag_order, step_heading=self.step_heading)

    def with_params(self, p: np.ndarray, std: np.ndarray | None = None) -> "CommandModel":
        p = np.asarray(p, float)
        nv, ny, _ = self.sizes
        kw = {"v_coef": p[:nv].copy(), "y_coef": p[nv:nv + ny].copy(), "w_coef": p[nv + ny:].copy()}
        if std is not None:
            std = np.asarray(std, float)
            kw.update(v_std=std[:nv], y_std=std[nv:nv + ny] if ny else None, w_std=std[nv + ny:])
        return replace(self, **kw)

    def basis(self, controls: np.ndarray, dt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n, Dv+1), (n, Dy+1) and (n, Dw+1) monomials of the scaled commands (the sideways one (n, 0) without
        ``vy``), with ``cross`` the scaled ``v`` last in the turn map's; with the steps' ``dt``, through the lag."""
        u = np.asarray(controls, float) / np.asarray(self.scale)
        nv, ny, nw = self.sizes
        bv, bw = u[:, 0:1] ** np.arange(nv), u[:, -1:] ** np.arange(nw - self.cross)
        if self.cross:
            bw = np.hstack([bw, u[:, 0:1]])
        by = u[:, 1:2] ** np.arange(ny) if ny else np.zeros((len(u), 0))
        if dt is None or self.lag <= 0:
            return bv, by, bw
        every = lagged(np.hstack([bv, by, bw]), dt, self.lag, self.lag_order)
        return every[:, :nv], every[:, nv:nv + ny], every[:, nv + ny:]

    def lag_memory(self, dt: np.ndarray) -> np.ndarray:
        """(T,) displacement over each step per unit of velocity offset the lag held when the log began (the
        velocity before the first command, unknown: at rest, or settled at another command), as its stages forget
        it: order 1 exp(-t/a), order 2 (1 + t/a) exp(-t/a), a = lag / order, integrated over the step."""
        return memory(dt, self.lag, self.lag_order)

    def velocities(self, controls: np.ndarray, dt: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) body-frame (forward, lateral, turn) velocity for each command row (steady state without ``dt``)."""
        bv, by, bw = self.basis(controls, dt)
        return np.column_stack([bv @ self.v_coef, by @ self.y_coef, bw @ self.w_coef])

    def step_velocities(self, log) -> np.ndarray:
        """(T, 3) the map at each step's ``v, w``, through the lag."""
        return self.velocities(log.controls, log.dt)

    def step_displacements(self, log) -> np.ndarray:
        """(T, 3) each step's displacement in its start frame: the map's velocity times the step's time, along the
        step's heading (:attr:`lead`)."""
        return factors.command.turned(self.step_velocities(log) * np.asarray(log.dt, float)[:, None], self.lead)

    def fitted_to_steps(self, log, moved: np.ndarray) -> "CommandModel":
        """The maps' regression on their basis of the steps' displacements ``moved`` (T, 3, start frame): forward on
        the v map, sideways on the vy map (none without ``vy``), turn on the w map, each step weighed by 1 / its
        length."""
        moved = factors.command.turned(moved, -self.lead)
        dt = np.asarray(log.dt, float)[:, None]
        w = 1.0 / np.sqrt(dt)            # a step's noise grows with its time (as the graph's motion factors say)
        parts = [np.linalg.lstsq(b * dt * w, moved[:, axis] * w[:, 0], rcond=None)[0] if b.shape[1] else np.zeros(0)
                 for b, axis in zip(self.basis(log.controls, log.dt), (0, 1, 2))]
        return self.with_params(np.concatenate(parts))

    def for_log(self, log, source: str = "the model") -> "CommandModel":
        """The map itself, after checking that ``log`` has the commands it maps."""
        if log.controls is None:
            raise LogError(f"{source} is a command map (continuous commands) and {log.source or 'the log'} runs "
                           f"discrete actions; calibrate this log first")
        if tuple(log.control_names) != tuple(self.commands):
            raise LogError(f"commands.csv: {source} maps commands '{','.join(self.commands)}' and this log has "
                           f"'{','.join(log.control_names)}'; calibrate this log first")
        return self

    def step_table(self, log) -> tuple[np.ndarray, VelocityTable]:
        """(T,) row of each step and the table they index: every step its own row, the map's velocity at that
        step turned to the step's heading, so that a table's step along its start heading moves as the map's step
        does (graph-em's E-step holds them fixed)."""
        return (np.arange(log.steps),
                VelocityTable(np.arange(log.steps), self.step_displacements(log) / np.asarray(log.dt, float)[:, None]))

    def std_json(self) -> dict:
        """The coefficients' posterior std for a JSON file (the uncertainty run's Laplace section)."""
        def lst(a):
            return None if a is None else np.asarray(a, float).tolist()
        out = {"command_std": {c: lst(self.coefficients(c)[1]) for c, *_ in self.maps}}
        if self.cross:
            out["command_cross_std"] = {"w": {"v": self.cross_coefficient("w")[1]}}
        return out

    def std_summary(self) -> tuple[str, str] | None:
        """(what, value) of the coefficients' posterior std, None before marginals."""
        if self.v_std is None:
            return None
        return ("command map coefficient std", "; ".join(
            f"{c} " + ", ".join(f"{x:.2g}" for x in self._map(c)[1]) for c, *_ in self.maps))

    def describe(self) -> str:
        return "continuous commands " + ",".join(self.commands)

    def model_fields(self) -> dict:
        """The :class:`casm_graph.models.model.Model` fields that hold this action model."""
        return {"command": self}

    def to_json(self) -> dict:
        def lst(a):
            return None if a is None else [float(x) for x in a]
        names = list(self.commands)
        return {"kind": KIND, "commands": names, **({"lateral": 0.0} if len(names) == 2 else {}),
                "scale": {c: float(s) for c, s in zip(names, self.scale)},
                "coefficients": {c: lst(self.coefficients(c)[0]) for c in names},
                "std": {c: lst(self.coefficients(c)[1]) for c in names},
                "command_range": {c: [float(x) for x in r] for c, r in zip(names, self.command_range)},
                "lag": float(self.lag), "lag_order": int(self.lag_order), "step_heading": self.step_heading,
                **({"cross": {"w": {"v": self.cross_coefficient("w")[0]}},
                    "cross_std": {"w": {"v": self.cross_coefficient("w")[1]}}} if self.cross else {})}

    @staticmethod
    def coefficients_in_units(am: dict) -> dict[str, tuple[list, list]]:
        """A command map's coefficients and std per command in the command's own units: model.json's divided by
        ``scale``^i (each log scales by its own largest command, so only these compare across logs). A cross term
        comes as the key ``"<map>_from_<other command>"``, divided by the other command's scale."""
        out = {}
        coefficients = am.get("coefficients")
        if not isinstance(coefficients, dict):
            return out
        std, scale = am.get("std") or {}, am.get("scale") or {}

        def of(c):
            s = json_number(scale.get(c, 1.0)) if isinstance(scale, dict) else 1.0
            return s if np.isfinite(s) and s > 0 else 1.0

        for c, coef in coefficients.items():
            s = of(c)
            sd = (std.get(c) if isinstance(std, dict) else None) or [None] * len(coef)
            out[c] = ([json_number(v) / s ** i for i, v in enumerate(coef)],
                      [(json_number(sd[i]) if i < len(sd) else np.nan) / s ** i for i in range(len(coef))])
        cross, cross_std = am.get("cross"), am.get("cross_std") or {}
        for c, terms in (cross.items() if isinstance(cross, dict) else ()):
            for o, v in (terms.items() if isinstance(terms, dict) else ()):
                sd = (cross_std.get(c) or {}).get(o) if isinstance(cross_std.get(c), dict) else None
                out[f"{c}_from_{o}"] = ([json_number(v) / of(o)], [json_number(sd) / of(o)])
        return out

    @staticmethod
    def figures(am: dict) -> list[tuple[str, str, float, float]]:
        """(name, family, value, std) of every figure of a command map's model.json entry ``am``: its coefficients
        in the command's own units."""
        return [(f"{c} coef {i}" if "_from_" not in c else c.replace("_", " "), "command_map", v, e)
                for c, (coef, sd) in CommandModel.coefficients_in_units(am).items()
                for i, (v, e) in enumerate(zip(coef, sd))]

    @staticmethod
    def brief(am: dict) -> dict:
        """A command map's model.json entry in brief, for a fleet's table: its coefficients in the command's units."""
        return {(f"{c}_coef_{i}" if "_from_" not in c else c): v
                for c, (coef, _) in CommandModel.coefficients_in_units(am).items() for i, v in enumerate(coef)}

    @classmethod
    def read(cls, w: Where, am: dict) -> "CommandModel":
        """The map of model.json's ``action_model`` entry ``am``, each field checked (``w`` names the file)."""
        scale = w.obj(am.get("scale"), "action_model.scale")
        coef = w.obj(am.get("coefficients"), "action_model.coefficients")
        std = w.obj(am.get("std") or {}, "action_model.std")
        rng = w.obj(am.get("command_range") or {}, "action_model.command_range")
        names = am.get("commands", ["v", "w"])
        if not isinstance(names, list) or tuple(names) not in COMMANDS:
            w.fail("action_model.commands", f"is {one_line(repr(names))[:40]}, expected "
                   + " or ".join(repr(list(c)) for c in COMMANDS))
        for c in names:
            w.num(scale.get(c), f"action_model.scale.{c}", positive=True)
            n = len(w.vec(coef.get(c), f"action_model.coefficients.{c}", max_len=MAX_POLY))
            if std.get(c) is not None:
                w.vec(std[c], f"action_model.std.{c}", n=n, nullable=True, nonneg=True)
            if c in rng:
                w.vec(rng[c], f"action_model.command_range.{c}", n=2)
        if "cross" in am:
            cross = w.obj(am["cross"], "action_model.cross")
            if tuple(names) != COMMANDS[0] or list(cross) != ["w"]:
                w.fail("action_model.cross", f"holds {one_line(repr(sorted(cross)))[:40]}; a cross term is the "
                       f"turn map's in v ('v, w' commands): {{\"w\": {{\"v\": ...}}}}")
            w.num(w.obj(cross["w"], "action_model.cross.w").get("v"), "action_model.cross.w.v")
        if "lag" in am:
            w.num(am["lag"], "action_model.lag", nonneg=True)
        if am.get("step_heading", "start") not in STEP_HEADINGS:
            w.fail("action_model.step_heading", f"is {one_line(repr(am['step_heading']))[:40]}, expected "
                   + " or ".join(repr(h) for h in STEP_HEADINGS))
        if am.get("lag_order", 1) not in (1, 2):
            w.fail("action_model.lag_order", f"is {one_line(repr(am['lag_order']))[:40]}, expected 1 or 2")
        return cls.from_json(am)

    @classmethod
    def from_json(cls, am: dict) -> "CommandModel":
        std = am.get("std") or {}
        rng = am.get("command_range") or {}
        names = tuple(am.get("commands") or ("v", "w"))
        if names not in COMMANDS:
            raise KeyError(f"commands must be one of {', '.join(','.join(c) for c in COMMANDS)}")

        def arr(d, c):
            return None if d.get(c) is None else np.array(d[c], float)

        side = {"y_coef": arr(am["coefficients"], names[1]), "y_std": arr(std, names[1])} if len(names) == 3 else {}
        coef = {c: arr(am["coefficients"], c) for c in (names[0], names[-1])}
        sd = {c: arr(std, c) for c in (names[0], names[-1])}
        cross = am.get("cross")
        if cross:                    # the turn map's coefficient in v goes last in its vector
            s = ((am.get("cross_std") or {}).get("w") or {}).get("v")
            coef["w"] = np.append(coef["w"], float(cross["w"]["v"]))
            sd["w"] = None if sd["w"] is None else np.append(sd["w"], np.nan if s is None else float(s))
        return cls(scale=tuple(float(am["scale"][c]) for c in names),
                   v_coef=coef[names[0]], w_coef=coef[names[-1]], v_std=sd[names[0]], w_std=sd[names[-1]],
                   cross=bool(cross),
                   command_range=tuple(tuple(rng.get(c, (0.0, 0.0))) for c in names),
                   lag=float(am.get("lag", 0.0)), lag_order=int(am.get("lag_order", 1)), commands=names,
                   step_heading=str(am.get("step_heading", "start")), **side)


def for_commands(controls: np.ndarray, v_degree: int = 2, w_degree: int = 1,
                 gain: float = 0.0, y_degree: int | None = None, cross: bool = False,
                 step_heading: str = "middle") -> CommandModel:
    """A model sized for ``controls`` (columns ``v, w``, or ``vx, vy, w``: a sideways map of ``y_degree``, default
    ``v_degree``): every map ``gain`` times the identity (0: the paper's zero start); ``cross`` (``v, w`` only)
    adds the turn map's term in ``v``, at 0; ``step_heading`` as :class:`CommandModel`'s."""
    controls = np.asarray(controls, float)
    names = COMMANDS[0] if controls.shape[1] == 2 else COMMANDS[1]
    scale = np.max(np.abs(controls), axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    cross = bool(cross) and len(names) == 2
    v, w = np.zeros(v_degree + 1), np.zeros(w_degree + 1 + cross)
    y = np.zeros((v_degree if y_degree is None else y_degree) + 1) if len(names) == 3 else np.zeros(0)
    v[1], w[1] = gain * scale[0], gain * scale[-1]
    if len(y):
        y[1] = gain * scale[1]
    rng = tuple((float(c.min()), float(c.max())) for c in controls.T)
    return CommandModel(scale=tuple(float(x) for x in scale), v_coef=v, w_coef=w, command_range=rng, commands=names,
                        y_coef=y, cross=cross, step_heading=step_heading)
