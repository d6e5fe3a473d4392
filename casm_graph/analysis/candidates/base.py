"""The candidate effects a diagnosis tries, fitted and scored against one base, one part per kind of action model.

The diagnosis (:func:`casm_graph.pipeline.diagnose.diagnose`) is one procedure: refit, test the residuals, score
the candidates, weigh them (:func:`~casm_graph.analysis.diagnosis.verdict`), challenge the verdict with the sparse
regression's proposal, name the look-alikes. Only the fitting and scoring of the candidates depends on the action
model: an action table's are refitted as the calibration fits them and scored held out too; a command map's are
settled on its coarse graph, the delays profiled."""
from __future__ import annotations

import numpy as np

from casm_graph.analysis.diagnosis import DEFAULTS, Candidate, DiagnoseOptions
from casm_graph.io.log import Log
from casm_graph.models.model import Model


class Bench:
    """A model refitted on a log (``fit``, its graph ``problem`` at ``state``, its ``poses`` at every step) and the
    candidate effects scored against it (:meth:`score`)."""

    kind = ""                 # the action models it serves (``model.action.kind``)
    last: tuple = ()          # effects a verdict names only after those with a structure (a mixture)

    def __init__(self, log: Log, model: Model, poses: np.ndarray, options: DiagnoseOptions = DEFAULTS,
                 extra_effects=(), candidates=None, workers: int = 2, client=None, progress=None, calibrated=None):
        """Refit ``model`` on ``log`` from ``poses`` (T+1, 3). ``extra_effects``: user effect classes to try too;
        ``candidates``: the effect names to try (None: every applicable one); ``workers``, ``client``: where the
        fits run; ``calibrated``: the calibration's options, when the model comes from one in memory."""
        self.log, self.options = log, options
        self.set_aside = 0                 # sightings the refit left out as gross outliers
        self.base_prediction = None        # the sightings the base the candidates are scored against predicts

    def score(self, structure: list[dict]) -> tuple[list[Candidate], dict, dict, dict]:
        """The candidates fitted and scored (lowest delta BIC first), the effects not tried with why, and by effect
        name the residual structure each is built for (``explains``) and what data separates it
        (``distinguished_by``). ``structure``: the residuals' strong dependences (held-out rounds are decided by them)."""
        raise NotImplementedError

    def refit_report(self, c: Candidate) -> dict | None:
        """The channel report of the log refitted with candidate ``c``'s fitted effect (its second line when its fit
        takes away a structure); None where this part does not refit so."""
        return None

    def challenge(self, cls) -> tuple[float, float]:
        """(log-likelihood gain, delta BIC) of the effect class ``cls`` (the sparse regression's proposal) scored as
        the candidates were."""
        raise NotImplementedError

    @property
    def relative(self) -> float:
        """Look-alikes also within this share of the best's delta BIC (0: the BIC margin and the predictions only)."""
        return 0.0

    def notes(self, candidates: list[Candidate]) -> list[str]:
        """Sentences the summary adds about how these candidates were scored."""
        return []

    def advice(self, proposal: dict) -> list[str]:
        """Sentences on where the action model itself can hold a proposal's terms (none by default)."""
        return []
