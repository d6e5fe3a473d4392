"""casm-graph: calibrate a robot's action and sensor models at once from one unlabelled log.

    import casm_graph as cg
    log = cg.load_log("LOG")
    cal = cg.calibrate(log)              # in memory; cal.summary(), cal.save("RUN")
    diag = cg.diagnose(log, cal)         # where the model fails, which effect is missing
    post = cg.uncertainty(log, cal)      # emcee on the noise levels, Laplace on the rest
"""
from casm_graph.analysis.diagnosis import DiagnoseOptions, Diagnosis
from casm_graph.analysis.groundtruth import evaluate as against_truth
from casm_graph.analysis.posterior import SamplerOptions
from casm_graph.analysis.proposal import ProposalOptions
from casm_graph.fit.calibration import CalibrateOptions, Calibration
from casm_graph.fit.continuous import CommandGraphOptions
from casm_graph.fit.methods.graph import GraphOptions
from casm_graph.fit.sensor_degree import SensorCurveOptions
from casm_graph.io.log import Log, LogError
from casm_graph.io.log import load as load_log
from casm_graph.io.mrclam import find_data as find_mrclam
from casm_graph.io.mrclam import load_robot as load_mrclam
from casm_graph.models.effects import Effect, catalog, register
from casm_graph.pipeline.calibrate import calibrate
from casm_graph.pipeline.diagnose import diagnose
from casm_graph.pipeline.hidden_effect import model_error
from casm_graph.pipeline.uncertainty import Uncertainty, uncertainty
from casm_graph.sim.protocols import simulate, write_log

__all__ = ["load_log", "simulate", "write_log", "calibrate", "diagnose", "uncertainty", "Effect", "register", "catalog",
           "model_error", "against_truth", "load_mrclam", "find_mrclam", "LogError", "Log", "CalibrateOptions",
           "Calibration", "GraphOptions", "CommandGraphOptions", "DiagnoseOptions", "Diagnosis", "Uncertainty", "ProposalOptions",
           "SamplerOptions", "SensorCurveOptions"]
