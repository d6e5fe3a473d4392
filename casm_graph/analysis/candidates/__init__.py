"""The candidates of a diagnosis, fitted and scored by the part for the model's kind of action model (:class:`Bench`)."""
from casm_graph.analysis.candidates.base import Bench
from casm_graph.analysis.candidates.command_poly import CommandBench
from casm_graph.analysis.candidates.table import TableBench

BENCHES: dict[str, type[Bench]] = {part.kind: part for part in (TableBench, CommandBench)}


def bench(kind: str) -> type[Bench]:
    """The part for action models of kind ``kind`` (a model's ``action.kind``)."""
    return BENCHES[kind]


__all__ = ["BENCHES", "Bench", "bench"]
