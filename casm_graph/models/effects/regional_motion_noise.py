"""regional_motion_noise: the motion noise differs by region of the floor (Milstein & Wang's dynamic motion models).

Per step of translation r and rotation theta the variances are k_r |r| and k_t |theta| + k_d |r|,
with (k_r, k_t, k_d) taken from the cell of a grid over the floor the robot is in. The parameters
are noise levels: the continuous-command graph sets them in its noise step (:func:`estimate`, the
maximum-likelihood fit of the expected squared motion errors), not by least squares.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from casm_graph.io.log import Log, LogError
from casm_graph.models.effects.base import Effect, register

VAR_FLOOR = 1e-8
GRID = (3, 2)                # regions along x and y
PAD = 0.3                    # m: the default floor reaches this far beyond the outermost landmarks
MIN_SEGMENTS = 30            # fewer motion segments in a region leave its k's where they were


def region_of(xy: np.ndarray, size, grid) -> np.ndarray:
    """Region id of each (x, y): row-major cells of the grid, clipped to the map."""
    xy = np.atleast_2d(xy)
    i = np.clip((xy[:, 0] / size[0] * grid[0]).astype(int), 0, grid[0] - 1)
    j = np.clip((xy[:, 1] / size[1] * grid[1]).astype(int), 0, grid[1] - 1)
    return j * grid[0] + i


def variances(k: np.ndarray, r: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Variance of the translation and of the rotation for reported (r, theta); ``k`` (..., 3)."""
    k = np.asarray(k, float)
    vr = k[..., 0] * np.abs(r) + VAR_FLOOR
    vt = k[..., 1] * np.abs(theta) + k[..., 2] * np.abs(r) + VAR_FLOOR
    return vr, vt


def estimate(r, theta, e_r2, e_t2, start) -> np.ndarray:
    """Maximum-likelihood (k_r, k_t, k_d) given the expected squared translation and rotation errors
    of steps with reported (r, theta): k_r in closed form, (k_t, k_d) by Nelder-Mead over their logs."""
    keep = np.abs(r) > 1e-9
    kr = max(float(np.mean(e_r2[keep] / np.abs(r[keep]))), VAR_FLOOR) if keep.any() else float(start[0])

    def f(z):
        vt = np.exp(z[0]) * np.abs(theta) + np.exp(z[1]) * np.abs(r) + VAR_FLOOR
        return float(0.5 * np.sum(np.log(vt) + e_t2 / vt))

    res = minimize(f, np.log(np.maximum(np.asarray(start, float)[1:], 1e-9)), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 600})
    return np.array([kr, *np.exp(res.x)])


@dataclass(frozen=True)
class Regions:
    """A grid of ``grid`` cells over the rectangle ``extent`` = (x0, y0, x1, y1), row-major from (x0, y0)."""

    extent: tuple[float, float, float, float]
    grid: tuple[int, int] = GRID

    @classmethod
    def around_landmarks(cls, log: Log, grid=GRID, pad: float = PAD) -> "Regions":
        lo, hi = log.landmark_xy.min(axis=0) - pad, log.landmark_xy.max(axis=0) + pad
        return cls((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), tuple(int(g) for g in grid))

    @classmethod
    def parse(cls, text: str | None, log: Log) -> "Regions | None":
        """The grid of ``--regions``: "NX,NY" (around the landmarks) or "NX,NY,X0,Y0,X1,Y1"; None for None (the
        default around the landmarks); LogError for anything else."""
        if text is None:
            return None
        try:
            v = [float(x) for x in text.split(",")]
        except ValueError:
            v = []
        if len(v) not in (2, 6) or v[0] < 1 or v[1] < 1 or v[0] != int(v[0]) or v[1] != int(v[1]) \
                or (len(v) == 6 and not (v[4] > v[2] and v[5] > v[3])):
            raise LogError(f"--regions {text!r}: give NX,NY or NX,NY,X0,Y0,X1,Y1 (whole counts >= 1, X1 > X0, "
                           f"Y1 > Y0)")
        grid = (int(v[0]), int(v[1]))
        if len(v) == 2:
            return cls.around_landmarks(log, grid)
        return cls(tuple(v[2:]), grid)

    @property
    def count(self) -> int:
        return self.grid[0] * self.grid[1]

    def of(self, xy: np.ndarray) -> np.ndarray:
        """Region id of each (x, y), clipped to the grid."""
        x0, y0, x1, y1 = self.extent
        return region_of(np.atleast_2d(xy) - [x0, y0], (x1 - x0, y1 - y0), self.grid)


def entry(regions: Regions, k: np.ndarray, segments=None) -> dict:
    """The model.json ``effects`` entry: the grid, its extent, each region's k's and how many motion
    segments fixed them (fewer than ``MIN_SEGMENTS``: the region is undetermined, its k's are the start)."""
    k = np.asarray(k, float)
    out = {"grid": list(regions.grid), "extent": list(regions.extent),
           "k_r": k[:, 0].tolist(), "k_t": k[:, 1].tolist(), "k_d": k[:, 2].tolist()}
    if segments is not None:
        out["segments"] = [int(n) for n in segments]
    return out


def determined(e: dict) -> np.ndarray:
    """Which regions of a model.json entry had enough segments to fix their k's."""
    n = len(e["k_r"])
    return np.asarray(e.get("segments", [0] * n)) >= MIN_SEGMENTS


def from_entry(e: dict) -> tuple[Regions, np.ndarray]:
    """(regions, (R, 3) k's) of a model.json ``effects`` entry."""
    return (Regions(tuple(float(v) for v in e["extent"]), tuple(int(g) for g in e["grid"])),
            np.column_stack([e["k_r"], e["k_t"], e["k_d"]]).astype(float))


@register
class RegionalMotionNoise(Effect):
    name = "regional_motion_noise"
    channel = "motion"
    map_bound = True
    params = ("k_r", "k_t", "k_d")          # per region of the grid
    start = (0.002, 0.01, 0.002)
    scale = (0.002, 0.01, 0.002)
    noise_only = True
    continuous_only = True
    explains = (("forward", "x"), ("forward", "y"), ("turn", "x"), ("turn", "y"))
    distinguished_by = ("each region visited often, in all directions: its noise, not its mean speed, differs "
                        "from the others'")
    physics = ("The floor is not uniform: on rough parts (carpet, gravel) each step's translation and rotation "
               "scatter more; per region of a grid the variances are k_r |r| and k_t |theta| + k_d |r| "
               "(range, turn and drift errors).")

    def applicable(self, log: Log) -> str | None:
        if log.controls is None or tuple(log.control_names or ()) != ("v", "w"):
            return "needs continuous (v, w) commands: its variances scale with each step's translation and rotation"
        return None

    def free_parameters(self) -> int:
        return len(self.params) * GRID[0] * GRID[1]
