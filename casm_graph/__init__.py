"""casm-graph: calibrate a robot's action and sensor models at once from one unlabelled log.

    import casm_graph as cg
    log = cg.load_log("LOG")
    cal = cg.calibrate(log)              # in memory; cal.summary(), cal.save("RUN")
    diag = cg.diagnose(log, cal)         # where the model fails, which effect is missing
    post = cg.uncertainty(log, cal)      # emcee on the noise levels, Laplace on the rest
"""
from .calibrate_run import calibrate
from .calibration import CalibrateOptions, Calibration
from .diagnose_run import diagnose
from .diagnosis import Diagnosis
from .effects import Effect, catalog, register
from .groundtruth import evaluate as against_truth
from .hidden_effect import model_error
from .log import Log, LogError
from .log import load as load_log
from .mrclam import find_data as find_mrclam
from .mrclam import load_robot as load_mrclam
from .simulators import simulate, write_log
from .uncertainty_run import Uncertainty, uncertainty

__all__ = ["load_log", "simulate", "write_log", "calibrate", "diagnose", "uncertainty", "Effect", "register", "catalog", "model_error", "LogError",
           "Log", "CalibrateOptions", "Calibration", "Diagnosis", "Uncertainty", "load_mrclam", "find_mrclam",
           "against_truth"]
