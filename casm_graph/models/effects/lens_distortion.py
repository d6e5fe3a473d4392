"""lens_distortion: the reading depends on where the landmark sits in the image.

An even polynomial in the image angle (a symmetric lens): order 1 scales by 1 + k a^2, order 2 adds k4 a^4
(a wide lens whose edges bend faster); the diagnosis keeps the member BIC prefers."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register


@register
class LensDistortion(Effect):
    name = "lens_distortion"
    scale_free = True
    channel = "sensor"
    params = ("k",)
    start = (0.0,)
    scale = (0.01,)
    orders = (1, 2)                  # even terms: a^2, then a^4
    order = 1
    explains = (("reading", "image_angle"),)
    distinguished_by = ("the same landmark seen at the edge and at the centre of the image from one distance: a "
                        "lens scales by the image angle, a misplaced landmark by the viewpoint")
    physics = ("A wide-angle lens magnifies the edges of the image differently from its centre, so a "
               "beacon's apparent height grows (k > 0) or shrinks with the square of its image angle (and its fourth "
               "power for a wide lens).")

    def applicable(self, log):
        """A camera reads the size and sees the bearing: both channels. Without ``pan`` the camera is fixed to the
        body and the image angle is the bearing (``Log.camera_pan``)."""
        lack = [c for c in ("reading", "bearing") if c not in log.channels]
        if lack:
            return (f"needs the {' and '.join(lack)} channel(s) (a camera reads the size and sees the bearing), "
                    f"which this log does not measure")
        return None

    def set_order(self, order: int) -> None:
        super().set_order(order)
        self.params = ("k", "k4")[:order]
        self.start, self.scale = (0.0,) * order, (0.01,) * order

    def reading(self, theta, predicted, ctx):
        a2 = np.nan_to_num(ctx["image_angle"]) ** 2
        return predicted * (1.0 + a2 * np.polyval(np.asarray(theta, float)[::-1], a2))
