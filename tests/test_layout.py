"""The package's folders follow the data flow: a module imports only from its own stage or earlier ones, and no
module imports another that (directly or not) imports it back."""
import ast
from pathlib import Path

import casm_graph

ORDER = ("io", "models", "graph", "fit", "analysis", "sim", "report", "baselines", "pipeline")
ROOT = Path(casm_graph.__file__).parent


def imports() -> dict[str, set[str]]:
    """Module -> the casm_graph modules it imports at module level (absolute names)."""
    out = {}
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        found = set()
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("casm_graph"):
                found.add(node.module)
                found.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                found.update(a.name for a in node.names if a.name.startswith("casm_graph"))
        out[name] = found
    return {m: {i for i in deps if i in out and i != m} for m, deps in out.items()}


def stage(module: str) -> int | None:
    parts = module.split(".")
    return ORDER.index(parts[1]) if len(parts) > 2 and parts[1] in ORDER else None


def test_imports_flow_one_way():
    wrong = [(m, i) for m, deps in imports().items() for i in deps
             if stage(m) is not None and stage(i) is not None and stage(i) > stage(m)]
    assert not wrong, "imports against the flow " + " > ".join(ORDER) + ": " + ", ".join(f"{m} -> {i}" for m, i in wrong)


def test_no_import_cycles():
    graph = imports()
    cycles = []

    def visit(m, path, seen):
        for n in graph[m]:
            if n == path[0]:
                cycles.append(path + [n])
            elif n not in seen and not n.startswith(path[0] + ".") and len(path) < 12:
                seen.add(n)
                visit(n, path + [n], seen)

    for m in graph:
        visit(m, [m], set())
    real = [c for c in cycles if not all(x == c[0] or x.startswith(c[0] + ".") or c[0].startswith(x + ".")
                                         for x in c)]
    assert not real, "import cycles: " + "; ".join(" -> ".join(c) for c in real[:5])
