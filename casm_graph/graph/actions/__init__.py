"""Action-model parts of the graph, by name (:class:`casm_graph.graph.actions.base.ActionPart`)."""
from casm_graph.graph.actions.base import ActionPart
from casm_graph.graph.actions.command_poly import CommandPoly
from casm_graph.graph.actions.table import TableActions

ACTIONS: dict[str, type[ActionPart]] = {TableActions.name: TableActions, CommandPoly.name: CommandPoly}


def part_for(lay) -> type[ActionPart]:
    """The action part whose layout ``lay`` is (graph-em's E-step lays a command log out as a table of one
    pseudo-action per step, so the layout, not the model, decides)."""
    return next(part for part in ACTIONS.values() if isinstance(lay, part.layout_type))


def default_layout(log, model):
    """The layout of a graph of ``model`` on ``log`` when the caller gives none: its action part's
    (:meth:`ActionPart.default_layout`)."""
    return ACTIONS[model.action.kind].default_layout(log, model)


__all__ = ["ACTIONS", "ActionPart", "CommandPoly", "TableActions", "default_layout", "part_for"]
