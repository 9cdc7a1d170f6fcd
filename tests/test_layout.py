"""The package's shape (issue 17): no import circle among relicgpu's modules, not even one made
by an import inside a function; no module much over 500 lines; the CLI only at the top.

Read from the sources with `ast`: an import inside a function (kept where it defers an optional
dependency such as Warp or torch) is an edge like any other, so a circle that only shows at
call time fails too.
"""
from __future__ import annotations

import ast
import subprocess
import sys
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


def _imports(name: str, path: Path, modules: dict) -> list[str]:
    """The relicgpu modules the file imports, at module level or inside a function."""
    tree = ast.parse(path.read_text())
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
                out.append(target)
    return out


MODULES = _modules()
EDGES = {name: _imports(name, path, MODULES) for name, path in MODULES.items()}


def _circles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    graph = {m: sorted(set(EDGES[m])) for m in MODULES}
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
    users = sorted(m for m, edges in EDGES.items() if "relicgpu.cli" in edges)
    assert users == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_length(name):
    assert MODULES[name].read_text().count("\n") <= MAX_LINES


def test_a_command_loads_only_its_own_module():
    # `relicgpu synth` must not pay for Flask or the matching stages (start-up time, optional extras)
    code = ("import sys, relicgpu.cli as c; c._parser_for('synth'); "
            "print(sorted(m for m in ('flask', 'relicgpu.heap.assembly', 'relicgpu.pair.pipeline') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
