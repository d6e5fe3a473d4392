"""The EKFS-EM paper's Aibo: its field and beacons (m), and its 40-action command set (attempted vx, vy, w)."""
from __future__ import annotations

import numpy as np

FIELD = (5.4, 3.6)
BEACONS = np.array([[1.35, 1.95], [-1.35, 1.95], [1.35, -1.95], [-1.35, -1.95]])
TURNS = (-1 / 2, -1 / 6, 0.0, 1 / 6, 1 / 2)
DIRECTIONS = (0.0, np.pi / 4, np.pi / 2, 3 * np.pi / 4, np.pi, -3 * np.pi / 4, -np.pi / 2, -np.pi / 4)


def attempted_table() -> np.ndarray:
    """(40, 3) attempted velocities, normalised so vx^2 + vy^2 + w^2 = 1; row = action id."""
    rows = []
    for a in TURNS:
        r = np.sqrt(1.0 - a * a)
        for b in DIRECTIONS:
            rows.append((r * np.cos(b), r * np.sin(b), a))
    return np.array(rows)

