"""Architecture: doe/fab/layouts never import torch; only psf_learn may."""

import ast
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def imported_modules(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module


def test_no_torch_outside_psf_learn():
    offenders = [
        f"{p.relative_to(ROOT)}: {m}"
        for pkg in ("doe", "fab", "layouts")
        for p in (ROOT / pkg).rglob("*.py")
        for m in imported_modules(p)
        if m == "torch" or m.startswith("torch.")
    ]
    assert not offenders, offenders


def test_cli_help_does_not_load_torch():
    code = (
        "import sys; from doe.cli import build_parser; build_parser(); "
        "print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
