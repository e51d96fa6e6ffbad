"""Architecture: the house's rules, read from the source with ``ast``.

- sizes: no module over 500 lines, no function over 100 (``SIZE_EXCEPTIONS`` aside,
  each named with its reason in docs/architecture.md);
- no import circle among the project's modules (module-level and deferred imports);
- nothing imports a command module (``*.commands.*``) but the dispatcher, tests and
  benchmarks included;
- layers: layouts -> doe -> fab / psf_learn (-> bench); only psf_learn imports torch;
- stage files (``learn.json``, ...) are named only in ``doe/records``; doe's optics core
  reads no stage file;
- no ``try: import <project module> except ImportError``.

Each check is a function of the repository root that returns its offenders, so that
``test_each_check_catches_a_violation`` can run it on a small tree with faults planted.
"""

import ast
import pathlib
import re
import subprocess
import sys
from dataclasses import dataclass

import networkx as nx
import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

PACKAGES = ("doe", "fab", "layouts", "psf_learn")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 100
# Modules ("fab/x.py") or functions ("fab/x.py::Class.method") allowed over the limits;
# docs/architecture.md ("Exceptions") names each one with the same reason.
SIZE_EXCEPTIONS: dict[str, str] = {}

DISPATCHER = "doe.infra.cli"  # the one importer of command modules
# The packages each package may import (bench, tests: any).
LAYERS = {
    "layouts": {"layouts"},
    "doe": {"doe", "layouts"},
    "fab": {"fab", "doe", "layouts"},
    "psf_learn": {"psf_learn", "doe", "layouts"},
}
TORCH_PACKAGE = "psf_learn"
STAGE_FILES = (
    "learn.json",
    "retrieval.json",
    "fab_manifest.json",
    "verify.json",
    "mesh_report.json",
    "camera.json",
)
RECORDS = "doe.records"
# doe's rooms that are not the optics core (doe.retrieve and doe.camera_stage: the
# retrieve and camera stages' libraries, which read and write their files through doe.records)
NOT_OPTICS = ("doe.infra", "doe.records", "doe.commands", "doe.retrieve", "doe.camera_stage")
# Calls whose first argument, a string, names a module (or an attribute of one).
MODULE_NAMING_CALLS = {"import_module", "__import__", "importorskip", "patch", "setattr", "delattr"}
IMPORT_ERRORS = {"ImportError", "ModuleNotFoundError", "Exception", "BaseException"}


# --- reading the source ---------------------------------------------------------------


def module_name(path, root):
    """Return the dotted module name of ``path`` (a package's ``__init__``: the package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_modules(root):
    """Return {module name: path} of every module of the project's packages."""
    return {
        module_name(p, root): p
        for pkg in PACKAGES
        if (root / pkg).is_dir()
        for p in sorted((root / pkg).rglob("*.py"))
    }


def script_files(root):
    """Return the Python files of tests/ and bench/ (scripts, not part of the packages)."""
    return [
        p
        for d in ("tests", "bench")
        if (root / d).is_dir()
        for p in sorted((root / d).rglob("*.py"))
    ]


def parse(path):
    return ast.parse(path.read_text(), filename=str(path))


@dataclass(frozen=True)
class Import:
    """One module named by an import statement (or an import-like call) of a file."""

    target: str  # dotted name, resolved against the known modules where it names one
    names: tuple[str, ...]  # the names a from-import takes from ``target``
    line: int


def imports(tree, name, is_package, known):
    """Return the Imports of a parsed module, deferred ones (in functions) included.

    ``from pkg import mod`` names the module ``pkg.mod`` where that is one of ``known``;
    calls such as ``importlib.import_module("x")`` or ``monkeypatch.setattr("x.y", v)``
    name ``x``; the dispatcher's ``COMMAND_MODULES`` names the modules it loads.
    """
    package = name.split(".") if is_package else name.split(".")[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [Import(a.name, (), node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package[: len(package) - (node.level - 1)]
                base = ".".join(parent + ([node.module] if node.module else []))
            taken = []
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in known:
                    found.append(Import(sub, (), node.lineno))
                else:
                    taken.append(alias.name)
            if taken:
                found.append(Import(base, tuple(taken), node.lineno))
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            first = node.args[0]
            if (
                called in MODULE_NAMING_CALLS
                and isinstance(first, ast.Constant)
                and isinstance(first.value, str)
                and re.fullmatch(r"[A-Za-z_]\w*(\.\w+)*", first.value)
                and (
                    called in {"import_module", "__import__"}
                    or first.value.split(".")[0] in PACKAGES
                )
            ):
                found.append(Import(first.value, (), node.lineno))
        elif isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "COMMAND_MODULES" for t in node.targets
        ):
            if isinstance(node.value, (ast.Tuple, ast.List)):
                found += [
                    Import(e.value, (), e.lineno)
                    for e in node.value.elts
                    if isinstance(e, ast.Constant) and isinstance(e.value, str)
                ]
    return found


def known_module(target, known):
    """Return the longest prefix of ``target`` that is a known module (None if none is)."""
    while target and target not in known:
        target = target.rpartition(".")[0]
    return target or None


def project_imports(root):
    """Yield (module name, path, Import) for every import in the project's packages."""
    modules = package_modules(root)
    for name, path in modules.items():
        for imp in imports(parse(path), name, path.name == "__init__.py", modules):
            yield name, path, imp


def script_imports(root):
    """Yield (path, Import) for every import in tests/ and bench/."""
    modules = package_modules(root)
    for path in script_files(root):
        for imp in imports(parse(path), "__script__", False, modules):
            yield path, imp


def is_command_module(name):
    parts = name.split(".")
    return parts[0] in PACKAGES and "commands" in parts[1:]


def within(name, prefix):
    return name == prefix or name.startswith(prefix + ".")


def where(path, root, line=None):
    rel = path.relative_to(root).as_posix()
    return f"{rel}:{line}" if line is not None else rel


# --- the checks: each returns its offenders ---------------------------------------------


def function_lengths(tree):
    """Yield (qualified name, lines) of every def, nested and in classes included."""

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield prefix + child.name, child.end_lineno - child.lineno + 1
                yield from visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, f"{prefix}{child.name}.")
            else:
                yield from visit(child, prefix)

    yield from visit(tree, "")


def oversized(root):
    """Return {key: "key: N lines"} of modules and functions over the limits."""
    found = {}
    for path in package_modules(root).values():
        rel = where(path, root)
        lines = len(path.read_text().splitlines())
        if lines > MAX_MODULE_LINES:
            found[rel] = f"{rel}: {lines} lines (limit {MAX_MODULE_LINES})"
        for qualname, length in function_lengths(parse(path)):
            if length > MAX_FUNCTION_LINES:
                key = f"{rel}::{qualname}"
                found[key] = f"{key}: {length} lines (limit {MAX_FUNCTION_LINES})"
    return found


def import_graph(root):
    """Return the directed graph of imports among the project's modules (edge: line)."""
    modules = package_modules(root)
    graph = nx.DiGraph()
    graph.add_nodes_from(modules)
    for name, _, imp in project_imports(root):
        target = known_module(imp.target, modules)
        if target is not None and target != name and not graph.has_edge(name, target):
            graph.add_edge(name, target, line=imp.line)
    return graph


def import_circles(root):
    """Return one line per import circle: its modules, and one cycle with its import lines."""
    graph = import_graph(root)
    found = []
    for component in nx.strongly_connected_components(graph):
        if len(component) < 2:
            continue
        cycle = nx.find_cycle(graph.subgraph(component))
        path = " -> ".join(f"{a} (line {graph.edges[a, b]['line']})" for a, b in cycle)
        found.append(f"{sorted(component)}: {path} -> {cycle[0][0]}")
    return sorted(found)


def command_module_imports(root):
    """Return every import of a command module but the dispatcher's (tests, bench included)."""
    found = [
        f"{where(path, root, imp.line)}: {imp.target}"
        for name, path, imp in project_imports(root)
        if name != DISPATCHER and is_command_module(imp.target)
    ]
    found += [
        f"{where(path, root, imp.line)}: {imp.target}"
        for path, imp in script_imports(root)
        if is_command_module(imp.target)
    ]
    return found


def layer_violations(root):
    """Return every import that crosses the layers the wrong way, torch outside psf_learn."""
    found = []
    for name, path, imp in project_imports(root):
        own, other = name.split(".")[0], imp.target.split(".")[0]
        if other == "torch" and own != TORCH_PACKAGE:
            found.append(f"{where(path, root, imp.line)}: {imp.target} (only {TORCH_PACKAGE})")
        elif other in PACKAGES and other not in LAYERS[own]:
            if name == DISPATCHER and is_command_module(imp.target):
                continue  # the dispatcher loads every package's commands
            found.append(f"{where(path, root, imp.line)}: {own} imports {imp.target}")
    return found


def string_constants(tree):
    """Yield the str Constant nodes that are values (docstrings and bare strings left out)."""
    bare = {
        id(node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in bare:
            yield node


STAGE_FILE_PATH = re.compile(r"(?:^|[/\\])(" + "|".join(re.escape(f) for f in STAGE_FILES) + r")$")


def stage_file_names(root):
    """Return every string constant outside doe/records that names a stage file as a path.

    A constant that is the file name, or a path ending in it (an f-string's
    ``"/learn.json"`` part too): code that builds the file's path. Prose that
    mentions a file (a flag's help, a message) is left alone.
    """
    return [
        f"{where(path, root, node.lineno)}: {node.value!r}"
        for name, path in package_modules(root).items()
        if not within(name, RECORDS)
        for node in string_constants(parse(path))
        if STAGE_FILE_PATH.search(node.value.strip())
    ]


def optics_reading_files(root):
    """Return the imports by which doe's optics core could read a stage file."""
    found = []
    for name, path, imp in project_imports(root):
        if not within(name, "doe") or any(within(name, room) for room in NOT_OPTICS):
            continue
        reads = (
            within(imp.target, RECORDS)
            or imp.target == "json"
            or (imp.target == "doe.infra.files" and "read_json" in imp.names)
        )
        if reads:
            found.append(f"{where(path, root, imp.line)}: {imp.target} {list(imp.names)}")
    return found


def guarded_project_imports(root):
    """Return every import of the project's own modules inside try/except ImportError."""
    modules = package_modules(root)
    files = [(n, p) for n, p in modules.items()] + [("__script__", p) for p in script_files(root)]
    found = []
    for name, path in files:
        tree = parse(path)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Try) or not any(map(_catches_import_error, node.handlers)):
                continue
            body = ast.Module(body=node.body, type_ignores=[])
            for imp in imports(body, name, path.name == "__init__.py", modules):
                if imp.target.split(".")[0] in PACKAGES or imp.target == "":
                    found.append(f"{where(path, root, imp.line)}: {imp.target}")
    return found


def _catches_import_error(handler):
    if handler.type is None:
        return True
    kinds = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(
        (k.id if isinstance(k, ast.Name) else getattr(k, "attr", None)) in IMPORT_ERRORS
        for k in kinds
    )


def refuse(header, offenders):
    """Fail with ``header`` and the offenders, one a line, in path and line order."""

    def order(line):
        return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", line)]

    if offenders:
        lines = "\n  ".join(sorted(offenders, key=order))
        pytest.fail(f"{header} ({len(offenders)}):\n  {lines}", pytrace=False)


# --- the tests ---------------------------------------------------------------------------


def test_no_module_or_function_over_the_limits():
    found = oversized(ROOT)
    offenders = [line for key, line in found.items() if key not in SIZE_EXCEPTIONS]
    refuse(
        f"over {MAX_MODULE_LINES} lines a module or {MAX_FUNCTION_LINES} a function "
        "(split it, or name it in SIZE_EXCEPTIONS and docs/architecture.md)",
        offenders,
    )


def test_size_exceptions_are_needed_and_named_in_the_docs():
    stale = sorted(set(SIZE_EXCEPTIONS) - set(oversized(ROOT)))
    refuse("SIZE_EXCEPTIONS within the limits now (drop them)", stale)
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = re.search(r"^## Exceptions\b.*?(?=^## |\Z)", text, re.M | re.S)
    assert section, "docs/architecture.md has no '## Exceptions' section"
    # one list item per exception: "- `fab/x.py::name`: the reason"
    named = set(re.findall(r"^[-*] `([\w/]+\.py(?:::[\w.]+)?)`", section.group(), re.M))
    assert named == set(SIZE_EXCEPTIONS), (
        f"docs/architecture.md names {sorted(named)}, SIZE_EXCEPTIONS {sorted(SIZE_EXCEPTIONS)}"
    )
    unexplained = [key for key, reason in SIZE_EXCEPTIONS.items() if not reason.strip()]
    refuse("SIZE_EXCEPTIONS without a reason", unexplained)


def test_no_import_circle():
    refuse("import circles (deferred imports count)", import_circles(ROOT))


def test_only_the_dispatcher_imports_command_modules():
    refuse(
        f"command modules imported outside {DISPATCHER} (call the stage's library, or "
        "the command through doe.infra.cli.main)",
        command_module_imports(ROOT),
    )


def test_layers():
    refuse(
        "imports against the layers layouts -> doe -> fab / psf_learn (torch: psf_learn)",
        layer_violations(ROOT),
    )


def test_stage_files_are_named_only_in_the_records():
    refuse(
        f"stage-file names outside {RECORDS} (import the name from its record module)",
        stage_file_names(ROOT),
    )


def test_optics_core_reads_no_stage_file():
    refuse(
        "doe's optics modules importing a file reader (stage files are read in doe.records)",
        optics_reading_files(ROOT),
    )


def test_no_try_except_import_error_around_project_modules():
    refuse(
        "the project's own modules imported in try/except ImportError",
        guarded_project_imports(ROOT),
    )


PLANTED = {
    # path: source; each file holds the faults one check must find (and prose it must not)
    "doe/__init__.py": "",
    "doe/infra/__init__.py": "",
    "doe/infra/cli.py": (
        "import importlib\n"
        "COMMAND_MODULES = ('fab.commands.run',)\n"  # allowed here
        "def main():\n    return importlib.import_module(COMMAND_MODULES[0])\n"
    ),
    "doe/records/__init__.py": "",
    "doe/records/learn.py": "LEARN_JSON = 'learn.json'\n",  # allowed here
    "doe/commands/__init__.py": "",
    "doe/commands/retrieve.py": (
        '"""Writes retrieval.json."""\n'  # a docstring: allowed
        "from doe.records.learn import LEARN_JSON\n"
        "HELP = 'the folder holding retrieval.json and levels.npy'\n"  # prose: allowed
        "def run(out):\n    return out / 'retrieval.json'\n"  # a path: caught
    ),
    "doe/optics.py": (
        "from doe.infra.files import read_json\n"  # the optics core reading files: caught
        "def f(d):\n    from fab.run import summary\n"  # layer: caught (and a circle)
        "    return read_json(f'{d}/verify.json')\n"  # caught
        + "\n".join(f"x{i} = {i}" for i in range(MAX_MODULE_LINES))  # too long: caught
        + "\n"
    ),
    "fab/__init__.py": "",
    "fab/commands/__init__.py": "",
    "fab/commands/run.py": "from doe.infra.cli import main\n",  # circle with the dispatcher
    "fab/commands/fab.py": "from fab.commands import run\n",  # a command module: caught
    "fab/run/__init__.py": "",
    "fab/run/summary.py": (
        "import torch\n"  # caught
        "from psf_learn import net\n"  # fab -> psf_learn: caught
        "from doe import optics\n"  # the other half of the circle
        "try:\n    from fab.commands import fab\nexcept ImportError:\n    fab = None\n"
        "def long():\n" + "    x = 1\n" * MAX_FUNCTION_LINES + "    return x\n"  # caught
    ),
    "layouts/__init__.py": "",
    "layouts/gds.py": "import doe.optics\n",  # layer: caught
    "psf_learn/__init__.py": "",
    "psf_learn/net.py": "import torch\n",  # allowed
    "tests/test_x.py": (
        "def test_x(monkeypatch):\n"
        "    monkeypatch.setattr('fab.commands.fab.run', None)\n"  # caught
        "    from doe.commands.retrieve import run\n"  # caught
    ),
    "bench/b.py": "import doe.commands.retrieve\n",  # caught
}

CAUGHT = {
    "oversized": ["doe/optics.py", "fab/run/summary.py::long"],
    "import_circles": ["doe.optics", "fab.run.summary", "doe.infra.cli", "fab.commands.run"],
    "command_module_imports": [
        "fab/commands/fab.py:1",
        "fab/run/summary.py:5",
        "tests/test_x.py:2",
        "tests/test_x.py:3",
        "bench/b.py:1",
    ],
    "layer_violations": [
        "fab/run/summary.py:1: torch",
        "fab imports psf_learn",
        "doe/optics.py:3: doe imports fab.run.summary",
        "layouts/gds.py:1: layouts imports doe.optics",
    ],
    "stage_file_names": ["doe/commands/retrieve.py:5", "doe/optics.py:4"],
    "optics_reading_files": ["doe/optics.py:1: doe.infra.files ['read_json']"],
    "guarded_project_imports": ["fab/run/summary.py:5: fab.commands.fab"],
}


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    root = tmp_path_factory.mktemp("planted")
    for rel, source in PLANTED.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(source)
    return root


@pytest.mark.parametrize("check", sorted(CAUGHT))
def test_each_check_catches_a_violation(planted, check):
    found = globals()[check](planted)
    report = "\n".join(found.values() if isinstance(found, dict) else found)
    for expected in CAUGHT[check]:
        assert expected in report, f"{check} missed {expected!r}; it found:\n{report}"
    allowed = ("'learn.json'", "HELP", "Writes retrieval", "psf_learn/net.py", "doe/infra/cli.py")
    assert not any(a in report for a in allowed), f"{check} found what is allowed:\n{report}"


def test_no_torch_outside_psf_learn():
    offenders = [
        f"{where(path, ROOT, imp.line)}: {imp.target}"
        for name, path, imp in project_imports(ROOT)
        if not within(name, TORCH_PACKAGE) and within(imp.target, "torch")
    ]
    refuse(f"torch imported outside {TORCH_PACKAGE}", offenders)


def test_cli_help_does_not_load_torch():
    code = (
        "import sys; from doe.infra.cli import build_parser; build_parser(); "
        "print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_python_dash_m_doe_is_the_doefab_command():
    # where no console script is on PATH (a venv not activated): python -m doe
    run = subprocess.run([sys.executable, "-m", "doe", "presets"], capture_output=True, text=True)
    assert run.returncode == 0 and "sun2020 (default): " in run.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "doe", "config", "show", "--config", "nope.toml"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "nope.toml" in bad.stderr


def test_learning_needs_no_layout_or_mesh_libraries(tmp_path):
    """A GPU node that only learns PSFs may lack gdstk, klayout, trimesh, nlopt, OpenImageIO.

    Loading the design (whose validation checks that the alignment marks fit) and a
    training step must not import them.
    """
    import imageio.v3 as iio

    (tmp_path / "img").mkdir()

    rng = np.random.default_rng(0)
    iio.imwrite(tmp_path / "img" / "a.png", rng.integers(0, 256, (96, 96), dtype=np.uint8))
    missing = ("gdstk", "klayout", "trimesh", "nlopt", "OpenImageIO", "build123d", "manifold3d")
    code = (
        "import sys\n"
        f"for m in {missing!r}: sys.modules[m] = None  # import m now raises ImportError\n"
        "from doe.infra.cli import main\n"
        f"sys.exit(main(['learn', '--out', {str(tmp_path / 'model')!r}, '--images', "
        f"{str(tmp_path / 'img')!r}, '--steps', '1', '--batch', '2']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "model" / "psf.npy").exists()
