"""How the logs of one kind of action model are calibrated: where a calibration begins, what a request may ask
of it, and the fit with the requested effects. One part per kind; the methods and the pipelines look the part up
by the model's ``action.kind`` or the log's ``action_model_kind`` and never ask which kind a log has."""
from __future__ import annotations

from casm_graph.fit.result import Fit, Progress
from casm_graph.io.log import Log
from casm_graph.models.model import Model


class ActionKind:
    """The calibration of action models of kind ``name`` (:attr:`casm_graph.io.log.Log.action_model_kind`)."""

    name = ""
    step_heading = "start"       # the heading a step moves along unless the options say (CalibrateOptions.step_heading)

    def start_model(self, log: Log, sensor_degree: int = 3, basis: str = "distance", cross: bool = False,
                    step_heading: str = "start") -> Model:
        """The paper's start: zero velocities, a flat sensor curve of ``sensor_degree`` in ``basis`` (``cross``:
        the turn map of ``v, w`` commands also linear in ``v``; ``step_heading``: the heading a command step moves
        along; a table has neither)."""
        raise NotImplementedError

    def initialise(self, log: Log, start: Model):
        """The start from nothing but the log (``.model``, ``.poses`` at every step)."""
        raise NotImplementedError

    def coarse(self, log: Log, start: Model, seed: int = 0, progress: Progress | None = None, options=None):
        """The log-only start settled on the coarse graph (``.model``, ``.poses`` at every step); ``options``:
        the table graph's :class:`~casm_graph.fit.methods.graph.GraphOptions` (a command map's graph keeps its
        own)."""
        raise NotImplementedError

    def check(self, log: Log, options, classes: list) -> None:
        """LogError, before any work, when ``log`` cannot be calibrated as ``options`` (a
        :class:`~casm_graph.fit.calibration.CalibrateOptions`) ask, with the effect ``classes``."""

    def calibrate(self, log: Log, start: Model, options, classes: list,
                  progress: Progress | None = None) -> Fit:
        """The fit of ``log`` from ``start`` by ``options.method``, with the effect ``classes``."""
        raise NotImplementedError
