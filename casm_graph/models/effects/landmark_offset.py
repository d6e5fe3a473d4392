"""landmark_offset: a landmark stands somewhere other than the map says."""
from __future__ import annotations

import numpy as np

from casm_graph.models.aibo import BEACONS
from casm_graph.models.effects.base import Effect, register

PRIOR_SIGMA = 0.5   # m, on each shape coordinate


def shape_basis(xy: np.ndarray) -> np.ndarray:
    """(2L, 2L-4) orthonormal offsets of the landmarks that change the map's shape.

    Moving, turning or scaling every landmark together is undetectable (the path, the velocity
    table and the sensor curve follow), so only the remaining 2L-4 directions are parameters.
    """
    c = xy - xy.mean(axis=0)
    sim = np.stack([np.tile([1.0, 0.0], len(xy)), np.tile([0.0, 1.0], len(xy)),
                    np.column_stack([-c[:, 1], c[:, 0]]).ravel(), c.ravel()], axis=1)
    u, _, _ = np.linalg.svd(sim, full_matrices=True)
    return u[:, 4:]


@register
class LandmarkOffset(Effect):
    name = "landmark_offset"
    channel = "sensor"
    explains = (("reading", "landmark"), ("bearing", "landmark"), ("reading", "x"), ("reading", "y"),
                ("bearing", "x"), ("bearing", "y"))
    distinguished_by = ("each landmark seen from several sides: a misplaced landmark biases the sightings by the "
                        "side it is seen from, a distorting lens by the image angle")
    physics = ("The map is wrong about a landmark: it was knocked or measured carelessly, so sightings "
               "of it disagree with the others in both distance and direction.")

    def __init__(self, log=None):
        super().__init__(log)
        if log is not None:
            self.ids, xy = log.landmark_ids, log.landmark_xy
        else:
            self.ids, xy = np.arange(len(BEACONS)), BEACONS
        self.Q = shape_basis(np.asarray(xy, float))
        self.params = tuple(f"shape_{k + 1}" for k in range(self.Q.shape[1]))
        self.start = tuple(0.0 for _ in self.params)
        self.scale = tuple(0.01 for _ in self.params)

    def applicable(self, log):
        if len(log.landmark_ids) < 3:
            return "needs at least three landmarks (with fewer, a misplaced one cannot be told from the path)"
        return None

    def prior(self):
        return np.zeros(len(self.params)), np.full(len(self.params), PRIOR_SIGMA)

    def offsets(self, theta) -> np.ndarray:
        """(L, 2) landmark offsets: shape coordinates, or raw offsets (the simulator's truth)."""
        theta = np.asarray(theta, float)
        raw = theta if len(theta) == self.Q.shape[0] else self.Q @ theta
        return raw.reshape(-1, 2)

    def geometry(self, theta, pose, landmark_xy, ctx):
        return pose, landmark_xy + self.offsets(theta)[ctx["landmark"]]

    def simulate_params(self, value, rng):
        n = self.Q.shape[0] // 2
        off = np.zeros((n, 2))
        ang = rng.uniform(-np.pi, np.pi)
        off[int(rng.integers(n))] = value * np.array([np.cos(ang), np.sin(ang)])
        return off.ravel()

    def describe(self, theta):
        off = self.offsets(theta)
        out = {p: float(v) for p, v in zip(self.params, theta)} if len(theta) == len(self.params) else {}
        for i, (dx, dy) in zip(self.ids, off):
            out[f"dx_{int(i)}"], out[f"dy_{int(i)}"] = float(dx), float(dy)
        return out

    def shape_of(self, description: dict) -> np.ndarray:
        """Identifiable part of an offset description: its shape coordinates."""
        raw = np.array([[description[f"dx_{int(i)}"], description[f"dy_{int(i)}"]] for i in self.ids]).ravel()
        return self.Q.T @ raw
