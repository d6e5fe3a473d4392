"""The calibration of each kind of action model (:class:`ActionKind`), one part per kind, looked up by kind."""
from casm_graph.fit.methods.kinds.base import ActionKind
from casm_graph.fit.methods.kinds.command_poly import CommandKind
from casm_graph.fit.methods.kinds.table import TableKind

KINDS: dict[str, ActionKind] = {part.name: part for part in (TableKind(), CommandKind())}


def kind(name: str) -> ActionKind:
    """The part for action models of kind ``name`` (a model's ``action.kind``, a log's ``action_model_kind``)."""
    return KINDS[name]


__all__ = ["KINDS", "ActionKind", "kind"]
