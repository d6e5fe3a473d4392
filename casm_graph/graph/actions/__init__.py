"""Action-model parts of the graph, by name (:class:`casm_graph.graph.actions.base.ActionPart`)."""
from casm_graph.graph import table as G
from casm_graph.graph.actions.base import ActionPart
from casm_graph.graph.actions.command_poly import CommandPoly
from casm_graph.graph.actions.command_poly import layout as command_layout
from casm_graph.graph.actions.table import TableActions

ACTIONS: dict[str, type[ActionPart]] = {TableActions.name: TableActions, CommandPoly.name: CommandPoly}
DEFAULT_KNOT_DT = 0.25       # s between a command log's knots when the caller gives no layout (the fine graph's)


def kind_of(model, lay=None) -> str:
    """The action part a graph calls for: the one whose layout ``lay`` is, else the model's (a command map or a
    velocity table). graph-em's E-step gives a command log's model a table of one pseudo-action per step."""
    if lay is not None:
        return next(name for name, part in ACTIONS.items() if isinstance(lay, part.layout_type))
    return CommandPoly.name if model.command is not None else TableActions.name


def default_layout(log, model):
    """A pose at every step of an action-table log; knots every ``DEFAULT_KNOT_DT`` on a command log."""
    return command_layout(log, DEFAULT_KNOT_DT) if model.command is not None else G.layout(log, model, stride=1)


__all__ = ["ACTIONS", "ActionPart", "CommandPoly", "TableActions", "default_layout", "kind_of"]
