"""What a calibration method returns (:class:`Fit`) and what it reports its progress to (:class:`Progress`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from casm_graph.models.model import Model

LIKELIHOOD_DROP = 20.0     # nats: a fit with effects this far below the same log's fit without them stopped short


@dataclass
class Fit:
    """What a method returns: the model, the poses at every pose step with their std, the cost trace."""

    model: Model
    poses: np.ndarray                 # (T+1, 3)
    pose_std: np.ndarray              # (T+1, 3) marginal std of x, y (map frame), theta; NaN when unknown
    cost: list[float] = field(default_factory=list)     # objective after each iteration
    stages: list[str] = field(default_factory=list)     # stage name of each cost entry
    iterations: int = 0
    converged: bool = False
    log_likelihood: float = float("nan")
    notes: dict = field(default_factory=dict)


class Progress:
    """Callbacks a method reports to; the command line shows them as a progress bar."""

    def stage(self, name: str, total: int | None = None, unit: str = "rounds") -> None: ...

    def step(self, n: int = 1, **info) -> None: ...
