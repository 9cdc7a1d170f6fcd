"""The package's shape (issue 17): no import circle among relicgpu's modules, not even one made
by an import inside a function; no module much over 500 lines; the CLI only at the top.

Read from the sources with `ast`: an import inside a function (kept where it defers an optional
dependency such as Warp or torch) is an edge like any other, so a circle that only shows at
call time fails too.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "relicgpu"
MAX_LINES = 520  # "about 500"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> list[tuple[str, int, bool]]:
    """(imported relicgpu module, line, at module level) for every import in the file."""
    tree = ast.parse(path.read_text())
    top = {id(node) for node in tree.body}
    top |= {id(n) for node in tree.body if isinstance(node, (ast.If, ast.Try)) for n in ast.walk(node)}
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            if target in modules and target != name:
                out.append((target, node.lineno, id(node) in top))
    return out


MODULES = _modules()
EDGES = {name: _imports(name, path, MODULES) for name, path in MODULES.items()}


def _circles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    graph = {m: sorted({t for t, _, _ in EDGES[m]}) for m in MODULES}
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for m in sorted(MODULES):
        if m not in index:
            visit(m)
    return found


def test_the_import_graph_has_no_circle():
    assert _circles() == []


def test_no_module_is_imported_by_name():
    # `import_module` hides an edge from the graph above; only the CLI's command table may use it
    users = sorted(m for m, p in MODULES.items() if "import_module(" in p.read_text())
    assert users in ([], ["relicgpu.cli"])


def test_only_the_cli_imports_the_cli():
    users = sorted(m for m, edges in EDGES.items() for t, _, _ in edges if t == "relicgpu.cli")
    assert users == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_length(name):
    assert MODULES[name].read_text().count("\n") <= MAX_LINES
