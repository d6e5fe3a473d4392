"""The calibrated model (INTERFACE section 3): action table, motion noise, sensor polynomial, sigmas."""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .log import Log, LogError

SCHEMA = "casm-graph/model/1"

# The EKFS-EM paper's start: zero velocities, a poor linear sensor model, wide sigmas.
PAPER_START_READING_SIGMA = 10.0
PAPER_START_BEARING_SIGMA = 0.2
PAPER_MOTION_NOISE = (0.010, 0.010, 0.1)


@dataclass
class Model:
    """Action table + sensor model; arrays indexed like ``action_ids``."""

    action_ids: np.ndarray
    velocities: np.ndarray                  # (A, 3) vx, vy, w
    reading_poly: np.ndarray                # c0..cD, reading = sum c_i d**i
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

    def reading(self, d) -> np.ndarray:
        return np.polynomial.polynomial.polyval(np.asarray(d, float), self.reading_poly)

    def reading_std(self, d) -> np.ndarray:
        """Posterior std of the sensor curve at distances ``d`` (from ``reading_poly_cov``; NaN without it)."""
        d = np.asarray(d, float)
        if self.reading_poly_cov is None:
            return np.full(d.shape, np.nan)
        V = np.vander(d.ravel(), len(self.reading_poly), increasing=True)
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
        return self.velocities[np.searchsorted(self.action_ids, action)]

    def with_(self, **kw) -> "Model":
        return replace(self, **kw)

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict:
        ids = [str(int(a)) for a in self.action_ids]
        std = self.velocity_std if self.velocity_std is not None else np.full_like(self.velocities, np.nan)
        sensor = {"reading_poly": self.reading_poly.tolist(),
                  "reading_sigma": float(self.reading_sigma),
                  "bearing_sigma": float(self.bearing_sigma),
                  "distance_range": [float(x) for x in self.distance_range]}
        if self.reading_poly_std is not None:
            sensor["reading_poly_std"] = self.reading_poly_std.tolist()
        if self.reading_poly_cov is not None:
            sensor["reading_poly_cov"] = np.asarray(self.reading_poly_cov).tolist()
            sensor["reading_band"] = self.reading_band()
        action_model = ({"kind": "table",
                         "velocities": {a: v.tolist() for a, v in zip(ids, self.velocities)},
                         "std": {a: [None if np.isnan(x) else float(x) for x in s]
                                 for a, s in zip(ids, std)}}
                        if self.command is None else self.command.to_json())
        return {
            "schema": SCHEMA,
            "action_model": action_model,
            "motion_noise": [float(x) for x in self.motion_noise],
            "sensor_model": sensor,
            "effects": self.effects,
            "fit": self.fit,
        }

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2))

    @classmethod
    def from_json(cls, data: dict, source: str = "model.json") -> "Model":
        try:
            if data.get("schema") != SCHEMA:
                raise LogError(f"{source}: schema is {data.get('schema')!r}, expected {SCHEMA!r}")
            am, sm = data["action_model"], data["sensor_model"]
            command = None
            if am.get("kind") == "command_poly":
                from .command_model import CommandModel
                command = CommandModel.from_json(am)
                am = {"kind": "table", "velocities": {}, "std": {}}
            if am.get("kind") != "table":
                raise LogError(f"{source}: action_model kind {am.get('kind')!r} is not supported here")
            ids = np.array(sorted(int(a) for a in am["velocities"]))
            vel = np.array([am["velocities"][str(a)] for a in ids], float).reshape(len(ids), 3)
            std = am.get("std")
            vstd = None
            if std:
                vstd = np.array([[np.nan if x is None else x for x in std[str(a)]] for a in ids], float)
            return cls(action_ids=ids, velocities=vel,
                       reading_poly=np.array(sm["reading_poly"], float),
                       reading_sigma=float(sm["reading_sigma"]),
                       bearing_sigma=float(sm["bearing_sigma"]),
                       motion_noise=np.array(data.get("motion_noise", PAPER_MOTION_NOISE), float),
                       distance_range=tuple(sm.get("distance_range", (0.0, 0.0))),
                       velocity_std=vstd,
                       reading_poly_std=(np.array(sm["reading_poly_std"], float)
                                         if "reading_poly_std" in sm else None),
                       reading_poly_cov=(np.array(sm["reading_poly_cov"], float)
                                         if "reading_poly_cov" in sm else None),
                       effects=data.get("effects", {}), fit=data.get("fit", {}), command=command)
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, LogError):
                raise
            raise LogError(f"{source}: not a casm-graph model ({type(exc).__name__}: {exc})") from None

    @classmethod
    def load(cls, path: str | Path) -> "Model":
        p = Path(path)
        if not p.is_file():
            raise LogError(f"{p}: missing model file")
        try:
            data = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise LogError(f"{p.name}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
        return cls.from_json(data, p.name)


def paper_start(log: Log, degree: int = 3) -> Model:
    """The EKFS-EM paper's starting point: zero velocities and a very poor linear sensor model.

    The line is flat at the median reading (it knows the readings' scale, nothing of their
    dependence on distance); higher coefficients start at zero.
    """
    if log.action is None:
        raise LogError("commands.csv: the table action model needs an 'action' column")
    ids = log.action_ids
    poly = np.zeros(degree + 1)
    poly[0] = float(np.nanmedian(log.obs_reading))
    return Model(action_ids=ids, velocities=np.zeros((len(ids), 3)), reading_poly=poly,
                 reading_sigma=PAPER_START_READING_SIGMA, bearing_sigma=PAPER_START_BEARING_SIGMA)
