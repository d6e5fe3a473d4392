"""Action-model parts of the graph, by name (:class:`casm_graph.graph.actions.base.ActionPart`)."""
from casm_graph.graph import table as G
from casm_graph.graph.actions.base import ActionPart
from casm_graph.graph.actions.command_poly import CommandPoly
from casm_graph.graph.actions.command_poly import layout as command_layout
from casm_graph.graph.actions.table import TableActions

ACTIONS: dict[str, type[ActionPart]] = {TableActions.name: TableActions, CommandPoly.name: CommandPoly}
DEFAULT_KNOT_DT = 0.25       # s between a command log's knots when the caller gives no layout (the fine graph's)


def part_for(lay) -> type[ActionPart]:
    """The action part whose layout ``lay`` is (graph-em's E-step lays a command log out as a table of one
    pseudo-action per step, so the layout, not the model, decides)."""
    return next(part for part in ACTIONS.values() if isinstance(lay, part.layout_type))


def default_layout(log, model):
    """A pose at every step of an action-table log; knots every ``DEFAULT_KNOT_DT`` on a command log."""
    return command_layout(log, DEFAULT_KNOT_DT) if model.command is not None else G.layout(log, model, stride=1)


__all__ = ["ACTIONS", "ActionPart", "CommandPoly", "TableActions", "default_layout", "part_for"]
