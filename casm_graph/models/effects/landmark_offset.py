"""landmark_offset: a landmark stands somewhere other than the map says."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from casm_graph.models.aibo import BEACONS
from casm_graph.models.effects.base import Effect, register

PRIOR_SIGMA = 0.5   # m, on each shape coordinate (at prior_width 1)
FRAME_SCALE = 0.005  # m: offsets beyond this count by their length, not its square, when the frame is chosen
FRAME_LANDMARKS = 5  # the frame is chosen from five landmarks up: with four, the three unmoved ones cannot outvote the
#                      moved one and the move's scale part, and often end farther off than in the shape's own frame


def rotation(phi: float) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s], [s, c]])


def onto_map(moved: np.ndarray, xy: np.ndarray, scale: bool = False) -> np.ndarray:
    """(phi, tx, ty, s) of the similarity x -> s R(phi) x + t that puts the ``moved`` landmarks (L, 2) where the map
    ``xy`` says, all but the few that moved: the one whose sum of distances is least (a soft L1 loss; the sum of
    squares would spread one landmark's move over the others). Without ``scale`` its scale is left out (s = 1):
    the path, the action model and the sensor curve must follow it, which not every model can."""
    c = xy.mean(axis=0)

    def apart(g):
        return np.linalg.norm(c + np.exp(g[3]) * (moved - c) @ rotation(g[0]).T + g[1:3] - xy, axis=1)
    g = least_squares(apart, np.zeros(4), loss="soft_l1", f_scale=FRAME_SCALE, x_scale=0.01).x
    s = float(np.exp(g[3])) if scale else 1.0
    return np.array([g[0], *(c - s * rotation(g[0]) @ c + g[1:3]), s])


def similar(g: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points ``xy`` (n, 2) moved by the similarity ``g`` = (phi, tx, ty[, s])."""
    return (g[3] if len(g) > 3 else 1.0) * xy @ rotation(g[0]).T + g[1:3]


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
    scale_free = True
    channel = "sensor"
    explains = (("reading", "landmark"), ("bearing", "landmark"), ("reading", "x"), ("reading", "y"),
                ("bearing", "x"), ("bearing", "y"))
    signature = "landmarks"
    distinguished_by = ("each landmark seen from several sides: a misplaced landmark biases the sightings by the "
                        "side it is seen from, a distorting lens by the image angle")
    prior_widths = (1.0, 0.2)        # a shape of five landmarks or more has directions the sightings hardly pin:
    #                                  under the loose prior alone some fits spread the move over every landmark
    physics = ("The map is wrong about a landmark: it was knocked or measured carelessly, so sightings "
               "of it disagree with the others in both distance and direction.")

    def __init__(self, log=None):
        super().__init__(log)
        if log is not None:
            self.ids, xy = log.landmark_ids, log.landmark_xy
        else:
            self.ids, xy = np.arange(len(BEACONS)), BEACONS
        self.xy = np.asarray(xy, float)
        self.Q = shape_basis(self.xy)
        self.frame = np.array([0.0, 0.0, 0.0, 1.0])   # (phi, tx, ty, s): the shape's landmarks onto the map
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
        """(L, 2) landmark offsets: shape coordinates in the effect's ``frame``, or raw offsets (the simulator's
        truth)."""
        theta = np.asarray(theta, float)
        if len(theta) == self.Q.shape[0]:
            return theta.reshape(-1, 2)
        moved = self.xy + (self.Q @ theta).reshape(-1, 2)
        return similar(self.frame, moved) - self.xy

    def reframe(self, theta, scale: bool = False) -> np.ndarray | None:
        """Move the ``frame`` so that the landmarks that did not move stay where the map says (:func:`onto_map`, its
        scale only with ``scale``), and return the similarity (phi, tx, ty, s) the poses must make with it: the
        likelihood does not change, but the path and the offsets are then in the map's own frame, the moved landmark
        carrying most of its offset. None with fewer than ``FRAME_LANDMARKS`` landmarks: too few stay put to outvote
        the moved one."""
        if len(self.xy) < FRAME_LANDMARKS:
            return None
        g = onto_map(self.xy + self.offsets(theta), self.xy, scale)
        f = self.frame
        self.frame = np.array([g[0] + f[0], *similar(g, f[None, 1:3])[0], g[3] * f[3]])
        return g

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
        if np.any(self.frame[:3] != 0) or self.frame[3] != 1:
            out["frame"] = [float(v) for v in (self.frame if self.frame[3] != 1 else self.frame[:3])]
        return {**out, **self.described_width()}

    def restore(self, entry: dict) -> None:
        """Take back the ``frame`` a model.json entry records (none: the shape's own; three numbers: no scale)."""
        super().restore(entry)
        self.frame = np.append(np.asarray(entry.get("frame", (0.0, 0.0, 0.0)), float), 1.0)[:4]

    def shape_of(self, description: dict) -> np.ndarray:
        """Identifiable part of an offset description: its shape coordinates."""
        raw = np.array([[description[f"dx_{int(i)}"], description[f"dy_{int(i)}"]] for i in self.ids]).ravel()
        return self.Q.T @ raw
