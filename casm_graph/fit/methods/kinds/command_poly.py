"""Calibrating a command map (continuous ``v,w`` or ``vx,vy,w`` commands): a zero map, the window start at the nominal map, the
coarse knots of :mod:`casm_graph.fit.continuous`; effects (profiled, regional noise, hooked) fitted on the graph,
from the fit of the method asked for, as an action table's are."""
from __future__ import annotations

from casm_graph.fit import continuous
from casm_graph.fit.methods.base import METHODS
from casm_graph.fit.methods.kinds.base import ActionKind
from casm_graph.models.command_model import KIND
from casm_graph.models.effects.regional_motion_noise import Regions


class CommandKind(ActionKind):
    name = KIND
    step_heading = "middle"      # a command held over a step drives an arc; its chord runs along the middle heading

    def start_model(self, log, sensor_degree=3, basis="distance", cross=False, step_heading="middle"):
        return continuous.start_model(log, sensor_degree, basis=basis, cross=cross, step_heading=step_heading)

    def initialise(self, log, start):
        return continuous.initialise(log, start)

    def coarse(self, log, start, seed=0, progress=None, options=None):
        return continuous.coarse_start(log, start, seed, progress)

    def check(self, log, options, classes):
        continuous.check_effects(options.effects, log)
        Regions.parse(options.regions, log)

    def calibrate(self, log, start, options, classes, progress=None):
        base = None
        if options.method != "graph":
            base = METHODS[options.method](log, start, seed=options.seed, progress=progress)
            if not classes:
                return base
        curve = {"max_sensor_degree": options.max_sensor_degree,
                 "free_basis": options.sensor_basis == "auto" and options.max_sensor_degree > options.sensor_degree,
                 "try_cross": options.cross_terms == "auto"}
        if classes:
            return continuous.fit_with_effects(log, start, list(options.effects), seed=options.seed,
                                               progress=progress, regions=Regions.parse(options.regions, log),
                                               options=options.command_graph, base=base, **curve)
        return continuous.fit(log, start, seed=options.seed, progress=progress, options=options.command_graph, **curve)
