"""The calibrated model (INTERFACE section 3): action table, motion noise, sensor polynomial, sigmas."""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from casm_graph.io.log import Log, LogError
from factors.reading import BASES, curve, features
from casm_graph.io.output import strict
from casm_graph.models.command_model import CommandModel
from casm_graph.models.effects import REGISTRY
from casm_graph.models.validate import COEFFICIENT_SPAN, MAX_POLY, SIGMA_SPAN, Where, no_constant, one_line
from casm_graph.models.velocity_table import VelocityTable

SCHEMA = "casm-graph/model/1"
ACTION_MODELS = {part.kind: part for part in (VelocityTable, CommandModel)}   # by model.json's action_model.kind

# The EKFS-EM paper's start: zero velocities, a poor linear sensor model, wide sigmas.
PAPER_START_READING_SIGMA = 10.0
PAPER_START_BEARING_SIGMA = 0.2
PAPER_MOTION_NOISE = (0.010, 0.010, 0.1)
CHANNELS = ("reading", "bearing")


@dataclass
class Model:
    """Action table + sensor model; arrays indexed like ``action_ids``."""

    action_ids: np.ndarray
    velocities: np.ndarray                  # (A, 3) vx, vy, w
    reading_poly: np.ndarray                # c0..cD, reading = sum c_i u**i, u = d (or 1/d: reading_basis)
    reading_sigma: float
    bearing_sigma: float
    motion_noise: np.ndarray = field(default_factory=lambda: np.array(PAPER_MOTION_NOISE))
    distance_range: tuple[float, float] = (0.0, 0.0)
    velocity_std: np.ndarray | None = None  # (A, 3) posterior std
    reading_poly_std: np.ndarray | None = None
    reading_poly_cov: np.ndarray | None = None  # (D+1, D+1) posterior covariance of the polynomial
    effects: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)
    command: object | None = None           # command_model.CommandModel for continuous commands
    channels: tuple[str, ...] = CHANNELS    # sensor channels the model was fitted on (the others are unknown)
    reading_basis: str = "distance"         # the curve's variable: "distance" or "inverse_distance" (factors.reading)

    def has(self, channel: str) -> bool:
        """Whether the model knows the sensor ``channel`` ('reading' or 'bearing')."""
        return channel in self.channels

    def noise_text(self, channel: str, spec: str = ".4g") -> str:
        """The channel's noise level formatted with ``spec``, or 'not measured' (a one-channel sensor)."""
        if not self.has(channel):
            return "not measured"
        return format(self.reading_sigma if channel == "reading" else self.bearing_sigma, spec)

    def curve_text(self, spec: str = ".5g") -> str:
        """The sensor polynomial's coefficients (in 1/d when that is its basis), or 'not measured' on a
        bearing-only model."""
        if not self.has("reading"):
            return "not measured"
        text = ", ".join(format(c, spec) for c in self.reading_poly)
        return text + (" (powers of 1/d)" if self.reading_basis == "inverse_distance" else "")

    def reading(self, d) -> np.ndarray:
        """The sensor curve at distances ``d``."""
        return curve(d, self.reading_poly, self.reading_basis)

    def reading_std(self, d) -> np.ndarray:
        """Posterior std of the sensor curve at distances ``d`` (from ``reading_poly_cov``; NaN without it)."""
        d = np.asarray(d, float)
        if self.reading_poly_cov is None:
            return np.full(d.shape, np.nan)
        V = features(d.ravel(), len(self.reading_poly), self.reading_basis)[0]
        var = np.einsum("ni,ij,nj->n", V, np.asarray(self.reading_poly_cov, float), V)
        return np.sqrt(np.clip(var, 0, None)).reshape(d.shape)

    def reading_band(self, points: int = 25) -> dict:
        """The sensor curve's 90 % credible band over the distances seen (Laplace: mean +- 1.645 std)."""
        d = np.linspace(*self.distance_range, points)
        m, s = self.reading(d), self.reading_std(d)
        return {"distance": d.tolist(), "reading": m.tolist(), "std": s.tolist(),
                "lo90": (m - 1.645 * s).tolist(), "hi90": (m + 1.645 * s).tolist()}

    def velocity_of(self, action: np.ndarray) -> np.ndarray:
        """(n, 3) velocity of each action id in ``action``."""
        return VelocityTable(self.action_ids, self.velocities).velocity_of(action)

    @property
    def action(self):
        """The action model: a :class:`VelocityTable` of discrete actions, or the continuous commands'
        :class:`casm_graph.models.command_model.CommandModel`. Both answer ``params``, ``with_params``,
        ``step_velocities``, ``step_displacements``, ``fitted_to_steps``, ``std_summary``, ``describe`` and
        ``to_json``."""
        if self.command is not None:
            return self.command
        return VelocityTable(self.action_ids, self.velocities, self.velocity_std)

    def with_action(self, action) -> "Model":
        """This model with the action model ``action`` (either kind)."""
        return self.with_(**action.model_fields())

    def with_action_params(self, p: np.ndarray, std: np.ndarray | None = None) -> "Model":
        """This model with the action model's parameter vector ``p`` (and its std when given)."""
        return self.with_action(self.action.with_params(p, std))

    def for_log(self, log, source: str = "the model") -> "Model":
        """This model ready to run on ``log``: a table indexed like its actions, a map checked against its
        commands; a :class:`LogError` saying why when the two do not fit together."""
        return self.with_action(self.action.for_log(log, source))

    def step_velocities(self, log) -> np.ndarray:
        """(T, 3) body-frame velocity of every command step of ``log``: the table's row for its action, or the
        command map at its ``v, w`` (through the map's lag)."""
        return self.action.step_velocities(log)

    def step_displacements(self, log) -> np.ndarray:
        """(T, 3) each command step's displacement in its start frame under the action model (a map's step along
        its heading :attr:`CommandModel.lead` of its turn on)."""
        return self.action.step_displacements(log)

    def fitted_to_steps(self, log, moved: np.ndarray) -> "Model":
        """The action model that best explains ``moved`` (T, 3), each step's body-frame displacement, by least
        squares (an EM M-step): each action's mean velocity, or the command map's regression on its basis."""
        return self.with_action(self.action.fitted_to_steps(log, moved))

    def scaled(self, s: float) -> "Model":
        """The same model on a map ``s`` times as large (poses and landmarks scaled about the origin): velocities,
        the motion noise's x and y and the distance range times ``s``, the sensor curve reading at distance d what
        it read at d / s; the sightings' likelihood does not change."""
        k = np.arange(len(self.reading_poly))
        f = float(s) ** (k if self.reading_basis == "inverse_distance" else -k)
        cov = self.reading_poly_cov
        return self.with_action(self.action.scaled(s)).with_(
            reading_poly=np.asarray(self.reading_poly, float) * f,
            reading_poly_std=None if self.reading_poly_std is None else np.asarray(self.reading_poly_std, float) * f,
            reading_poly_cov=None if cov is None else np.asarray(cov, float) * np.outer(f, f),
            motion_noise=np.asarray(self.motion_noise, float) * [s, s, 1.0],
            distance_range=tuple(float(d) * s for d in self.distance_range))

    def with_(self, **kw) -> "Model":
        return replace(self, **kw)

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict:
        """model.json's content, strict: every NaN or infinity is null (JSON has neither)."""
        reading = self.has("reading")
        sensor = {"channels": list(self.channels),
                  "reading_poly": self.reading_poly.tolist() if reading else None,
                  **({"reading_basis": self.reading_basis} if reading else {}),
                  "reading_sigma": float(self.reading_sigma) if reading else None,
                  "bearing_sigma": float(self.bearing_sigma) if self.has("bearing") else None,
                  "distance_range": [float(x) for x in self.distance_range]}
        if self.reading_poly_std is not None and reading:
            sensor["reading_poly_std"] = self.reading_poly_std.tolist()
        if self.reading_poly_cov is not None and reading:
            sensor["reading_poly_cov"] = np.asarray(self.reading_poly_cov).tolist()
            sensor["reading_band"] = self.reading_band()
        action_model = self.action.to_json()
        return strict({
            "schema": SCHEMA,
            "action_model": action_model,
            "motion_noise": [float(x) for x in self.motion_noise],
            "sensor_model": sensor,
            "effects": self.effects,
            "fit": self.fit,
        })

    def save(self, path: str | Path) -> None:
        """Write model.json (strict JSON: a NaN or infinity that slipped past ``to_json`` fails here)."""
        Path(path).write_text(json.dumps(self.to_json(), indent=2, allow_nan=False))

    @classmethod
    def from_json(cls, data, source: str = "model.json") -> "Model":
        """The model of a model.json document; anything malformed is one :class:`LogError` line."""
        try:
            return _from_json(cls, data, Where(source))
        except LogError:
            raise
        except RecursionError:
            raise LogError(f"{source}: nested too deeply to be a casm-graph model") from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:
            raise LogError(f"{source}: not a casm-graph model ({type(exc).__name__}: "
                           f"{one_line(str(exc))})") from None

    @classmethod
    def load(cls, path: str | Path) -> "Model":
        """Read RUN/model.json: strict UTF-8 JSON (no NaN or Infinity), then :meth:`from_json`."""
        p = Path(path)
        if not p.is_file():
            raise LogError(f"{p}: missing model file")
        try:
            text = p.read_bytes().decode("utf-8-sig")
        except OSError as exc:
            raise LogError(f"{p.name}: cannot be read ({exc.strerror or exc})") from None
        except UnicodeDecodeError as exc:
            raise LogError(f"{p.name}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
        try:
            data = json.loads(text, parse_constant=no_constant)
        except json.JSONDecodeError as exc:
            raise LogError(f"{p.name}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
        except RecursionError:
            raise LogError(f"{p.name}: not valid JSON for a model (nested too deeply)") from None
        except ValueError as exc:            # NaN/Infinity, or an integer too long to convert
            raise LogError(f"{p.name}: not valid JSON ({one_line(str(exc))})") from None
        return cls.from_json(data, p.name)


# --------------------------------------------------------------------------- reading model.json

def _effects(w: Where, effects) -> dict:
    w.obj(effects, "effects")
    for name, entry in effects.items():
        w.obj(entry, f"effects.{name}")
        w.plain(entry, f"effects.{name}")
        cls = REGISTRY.get(name)
        if cls is None:
            continue
        if not entry:
            continue
        if "grid" in entry or name == "regional_motion_noise":     # a field over the floor: its grid and extent
            grid = w.vec(entry.get("grid"), f"effects.{name}.grid", n=2, positive=True)
            if np.any(grid != np.round(grid)):
                w.fail(f"effects.{name}.grid", "must hold two whole counts")
        if entry.get("extent") is not None or name == "regional_motion_noise":
            ext = w.vec(entry.get("extent"), f"effects.{name}.extent", n=4)
            if not (ext[2] > ext[0] and ext[3] > ext[1]):
                w.fail(f"effects.{name}.extent", "must be [x0, y0, x1, y1] with x1 > x0 and y1 > y0")
        if entry.get("visits") is not None and "grid" in entry:
            v = w.vec(entry["visits"], f"effects.{name}.visits", n=int(grid.prod()), nonneg=True)
            if abs(float(np.sum(v)) - 1.0) > 1e-3:
                w.fail(f"effects.{name}.visits", "must be shares of the steps that sum to 1")
        if entry.get("frame") is not None:
            frame = w.vec(entry["frame"], f"effects.{name}.frame")
            if len(frame) not in (3, 4) or (len(frame) == 4 and not frame[3] > 0):
                w.fail(f"effects.{name}.frame", "must be [phi, tx, ty] or [phi, tx, ty, scale] with scale > 0")
        if entry.get("prior_width") is not None:
            w.num(entry["prior_width"], f"effects.{name}.prior_width", positive=True)
        if cls.orders and entry.get("order") is not None and entry["order"] not in cls.orders:
            w.fail(f"effects.{name}.order", f"must be one of {list(cls.orders)}")
        if name == "regional_motion_noise":
            for p in cls.params:
                w.vec(entry.get(p), f"effects.{name}.{p}", n=int(grid.prod()), nonneg=True)
            continue
        names = {p for k in cls.orders for p in cls.of_order(k)().params} | set(cls.params)   # every member's
        for p, v in entry.items():          # scalar parameters (landmark_offset's shape_k included)
            if p in names or p.startswith("shape_"):
                w.num(v, f"effects.{name}.{p}")
    return effects


def _from_json(cls, data, w: Where) -> Model:
    w.obj(data, "the top level")
    if data.get("schema") != SCHEMA:
        got = "missing" if data.get("schema") is None else one_line(repr(data["schema"]))[:60]
        w.fail("schema", f"is {got}, expected {SCHEMA!r}")
    am = w.obj(data.get("action_model"), "action_model")
    sm = w.obj(data.get("sensor_model"), "sensor_model")
    kind = am.get("kind")
    part = ACTION_MODELS.get(kind) if isinstance(kind, str) else None
    if part is None:
        w.fail("action_model.kind", f"{one_line(repr(kind))[:60]} is not supported here (known: "
                                    + ", ".join(map(repr, ACTION_MODELS)) + ")")
    action = {"action_ids": np.array([], np.int64), "velocities": np.zeros((0, 3)), **part.read(w, am).model_fields()}
    channels = sm.get("channels", list(CHANNELS))
    if (not isinstance(channels, list) or not channels or len(set(channels)) != len(channels)
            or not all(isinstance(c, str) and c in CHANNELS for c in channels)):
        w.fail("sensor_model.channels", f"must be a list of {' and/or '.join(map(repr, CHANNELS))} "
                                        f"(got {one_line(repr(channels))[:60]})")
    channels = tuple(c for c in CHANNELS if c in channels)
    reading = "reading" in channels
    poly = (w.vec(sm.get("reading_poly"), "sensor_model.reading_poly", max_len=MAX_POLY, span=COEFFICIENT_SPAN)
            if reading
            else np.zeros(2))      # a bearing-only model has no curve: a placeholder no one reads
    D = len(poly)
    basis = sm.get("reading_basis", "distance")
    if reading and basis not in BASES:
        w.fail("sensor_model.reading_basis", f"must be one of {', '.join(map(repr, BASES))} "
                                             f"(got {one_line(repr(basis))[:60]})")
    dr = w.vec(sm["distance_range"], "sensor_model.distance_range", n=2, nonneg=True) \
        if sm.get("distance_range") is not None else np.zeros(2)
    if dr[1] < dr[0]:
        w.fail("sensor_model.distance_range", f"must be [dmin, dmax] with dmin <= dmax (got {dr.tolist()})")
    poly_std = poly_cov = None
    if sm.get("reading_poly_std") is not None and reading:
        poly_std = w.vec(sm["reading_poly_std"], "sensor_model.reading_poly_std", n=D, nullable=True, nonneg=True)
    if sm.get("reading_poly_cov") is not None and reading:
        rows = sm["reading_poly_cov"]
        if not isinstance(rows, list) or len(rows) != D:
            w.fail("sensor_model.reading_poly_cov", f"must be a {D} x {D} matrix (one row per coefficient)")
        poly_cov = np.array([w.vec(r, f"sensor_model.reading_poly_cov[{i}]", n=D, nullable=True)
                             for i, r in enumerate(rows)], float)
        if np.isnan(poly_cov).any():
            poly_cov = None                 # written when the fit could not compute it: unknown
        elif not np.allclose(poly_cov, poly_cov.T, rtol=1e-6, atol=0) or np.any(np.diag(poly_cov) < 0):
            w.fail("sensor_model.reading_poly_cov", "must be a symmetric covariance (non-negative diagonal)")
    motion = (w.vec(data["motion_noise"], "motion_noise", n=3, positive=True, span=SIGMA_SPAN)
              if "motion_noise" in data else np.array(PAPER_MOTION_NOISE, float))
    effects = _effects(w, data.get("effects", {}))
    fit = w.obj(data.get("fit", {}), "fit")
    w.plain(fit, "fit")
    return cls(**action, reading_poly=poly,
               reading_sigma=(w.num(sm.get("reading_sigma"), "sensor_model.reading_sigma", positive=True, span=SIGMA_SPAN)
                              if reading else PAPER_START_READING_SIGMA),
               bearing_sigma=(w.num(sm.get("bearing_sigma"), "sensor_model.bearing_sigma", positive=True, span=SIGMA_SPAN)
                              if "bearing" in channels else PAPER_START_BEARING_SIGMA),
               channels=channels,
               motion_noise=motion, distance_range=(float(dr[0]), float(dr[1])),
               reading_poly_std=poly_std, reading_poly_cov=poly_cov, effects=effects, fit=fit,
               reading_basis=basis if reading else "distance")


def paper_start(log: Log, degree: int = 3, basis: str = "distance") -> Model:
    """The EKFS-EM paper's starting point: zero velocities and a very poor linear sensor model.

    The line is flat at the median reading (it knows the readings' scale, nothing of their
    dependence on distance); higher coefficients start at zero.
    """
    if log.action is None:
        raise LogError("commands.csv: the table action model needs an 'action' column")
    ids = log.action_ids
    poly = np.zeros(degree + 1)
    if "reading" in log.channels:
        poly[0] = float(np.nanmedian(log.obs_reading))
    return Model(action_ids=ids, velocities=np.zeros((len(ids), 3)), reading_poly=poly,
                 reading_sigma=PAPER_START_READING_SIGMA, bearing_sigma=PAPER_START_BEARING_SIGMA,
                 channels=log.channels, reading_basis=basis)
