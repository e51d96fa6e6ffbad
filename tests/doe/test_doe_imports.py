"""doe's modules import one another without a circle (deferred imports count)."""

import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _module_name(path):
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _doe_imports(path):
    """Every doe module that ``path`` imports, at module level or inside a function."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # "from doe import fraunhofer" imports the module doe.fraunhofer
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        yield from (name for name in names if name == "doe" or name.startswith("doe."))


def _graph():
    modules = {_module_name(p): p for p in (ROOT / "doe").rglob("*.py")}
    return {
        name: sorted({m for m in _doe_imports(path) if m in modules and m != name})
        for name, path in modules.items()
    }


def test_the_doe_modules_import_one_another_without_a_circle():
    graph, circles = _graph(), []

    def visit(name, path):
        for imported in graph[name]:
            if imported in path:
                circles.append(" -> ".join([*path[path.index(imported) :], imported]))
            elif imported not in done:
                visit(imported, [*path, imported])
        done.add(name)

    done = set()
    for name in sorted(graph):
        if name not in done:
            visit(name, [name])
    assert not circles, circles


def test_bounds_takes_the_goals_from_doe_goals_not_from_the_retrieval():
    assert "doe.goals" in _graph()["doe.bounds"]
    assert not [m for m in _graph()["doe.bounds"] if m.startswith("doe.retrieval")]


@pytest.mark.parametrize(
    "order", [("doe.bounds", "doe.retrieval"), ("doe.retrieval", "doe.bounds")]
)
def test_bounds_and_retrieval_import_in_either_order(order):
    code = f"import {order[0]}, {order[1]}; import doe.bounds as b; b.within_goals"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stderr
