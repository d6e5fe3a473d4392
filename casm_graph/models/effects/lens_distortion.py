"""lens_distortion: the reading depends on where the landmark sits in the image."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register


@register
class LensDistortion(Effect):
    name = "lens_distortion"
    channel = "sensor"
    params = ("k",)
    start = (0.0,)
    scale = (0.01,)
    explains = (("reading", "image_angle"),)
    distinguished_by = ("the same landmark seen at the edge and at the centre of the image from one distance: a "
                        "lens scales by the image angle, a misplaced landmark by the viewpoint")
    physics = ("A wide-angle lens magnifies the edges of the image differently from its centre, so a "
               "beacon's apparent height grows (k > 0) or shrinks with the square of its image angle.")

    def applicable(self, log):
        if log.obs_pan is None or np.all(np.isnan(log.obs_pan)):
            return "needs the camera pan angle (observations.csv column 'pan') to know the image angle"
        return None

    def reading(self, theta, predicted, ctx):
        ia = np.nan_to_num(ctx["image_angle"])
        return predicted * (1.0 + theta[0] * ia ** 2)
