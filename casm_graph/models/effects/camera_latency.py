"""camera_latency: an observation shows the world as it was a fixed delay before its time stamp."""
from __future__ import annotations

import numpy as np

from casm_graph.models.effects.base import Effect, register


@register
class CameraLatency(Effect):
    name = "camera_latency"
    scale_free = True
    channel = "sensor"
    params = ("delay",)
    start = (0.0,)
    scale = (0.005,)
    uses_velocity = True
    velocity_window = "delay"       # the image shows the pose the delay before: the mean velocity over it moves it there
    # the last two: a delay the smoothed poses take in (sightings that pin them) shows as motion trailing the commands
    explains = (("bearing", "turn_rate"), ("reading", "speed"), ("bearing", "speed"),
                ("forward", "acceleration"), ("turn", "turn_acceleration"))
    signature = "correlation"       # the smoothed poses take the delayed images in: the path trails the commands
    distinguished_by = ("turns of the body with the commands steady: the image trails the motion itself, while an"
                        " actuator lag delays only the motion after a command change")
    physics = ("Images take time to expose, transfer and process, so each sighting was taken where the "
               "robot was a little earlier: bearings lag behind turns by the delay times the turn rate.")

    def geometry(self, theta, pose, landmark_xy, ctx):
        v = ctx["velocity"]
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        back = theta[0]
        earlier = np.column_stack([pose[:, 0] - back * (c * v[:, 0] - s * v[:, 1]),
                                   pose[:, 1] - back * (s * v[:, 0] + c * v[:, 1]),
                                   pose[:, 2] - back * v[:, 2]])
        return earlier, landmark_xy
