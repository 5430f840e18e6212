"""The house's import rules (docs/design.md, "Rules of the house"; issue 46: "the import graph
still has no cycle"), read from the source with `ast`, nothing imported:

- no cycle among the modules of service/, models/ and bench/, counting imports inside functions
  too (a late import hides a cycle from Python, not from a reader);
- dependencies point one way: bench → service → models, never back (service/bench_command.py
  finds bench/ by name at run time, on purpose: the wheel ships without it);
- models/ is pure PyTorch: the standard library, torch and itself.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("models", "service", "bench")   # each may import only the ones before it (and itself)


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_modules() -> dict[str, Path]:
    return {module_name(p): p for top in LAYERS for p in sorted((REPO / top).rglob("*.py"))}


def imported_names(path: Path, name: str) -> set[str]:
    """Every module name an import statement anywhere in the file names, relative ones resolved;
    `from a import b` gives both a and a.b (b may be a submodule)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def import_graph() -> dict[str, set[str]]:
    """module → the modules of the three packages it imports (a name resolves to its longest
    module prefix: `service.loop.spec.LoopSpec` → service.loop.spec)."""
    modules = package_modules()

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    return {name: {target for imported in imported_names(path, name)
                   if (target := resolve(imported)) is not None and target != name}
            for name, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            for nxt in successors:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    assert len(graph) > 100 and "service.loop.loop" in graph["service.jobs.worker"]   # the graph is read
    assert cycles(graph) == []


def test_dependencies_point_from_bench_to_service_to_models_only():
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    upward = [f"{source} -> {target}" for source, targets in import_graph().items() for target in targets
              if rank[target.split(".")[0]] > rank[source.split(".")[0]]]
    assert upward == []


def test_models_imports_only_the_standard_library_and_torch():
    allowed = set(sys.stdlib_module_names) | {"torch", "models"}
    foreign = sorted(f"{module_name(path)}: {name}" for path in sorted((REPO / "models").rglob("*.py"))
                     for name in imported_names(path, module_name(path))
                     if name and name.split(".")[0] not in allowed)
    assert foreign == []
