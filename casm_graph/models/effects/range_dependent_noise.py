"""range_dependent_noise: the reading's noise grows with distance."""
from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from casm_graph.models.effects.base import Effect, register


@register
class RangeDependentNoise(Effect):
    name = "range_dependent_noise"
    channel = "sensor"
    params = ("growth",)
    start = (0.0,)
    scale = (0.05,)
    noise_only = True
    explains = (("reading", "distance"),)
    distinguished_by = ("sightings over a wide spread of distances: this noise grows with the distance, not with "
                        "the image angle or the landmark")
    physics = ("Far beacons cover few pixels, so edge quantisation and blur are a larger share of their "
               "height: the reading's noise grows linearly with distance, sigma (1 + growth d).")

    def applicable(self, log):
        return None if "reading" in log.channels else "needs the reading channel, which this log does not measure"

    def reading_scale(self, theta, distance, ctx):
        return 1.0 + max(theta[0], 0.0) * distance

    def estimate_noise(self, theta, reading_z, bearing_z, distance, ctx):
        r = reading_z * ctx["reading_scale"]            # back to residuals in units of sigma
        ok = np.isfinite(r) & (ctx["weight"] > 0.5)
        r, d = r[ok], distance[ok]

        def nll(g):
            s = 1.0 + g * d
            return 0.5 * len(r) * np.log(np.mean((r / s) ** 2)) + np.sum(np.log(s))

        best = minimize_scalar(nll, bounds=(0.0, 20.0), method="bounded", options={"xatol": 1e-4})
        return np.array([float(best.x)])
