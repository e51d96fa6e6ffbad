"""The manual's Python examples run: every ```python block of the pages below.

Each example runs in a folder of its own that holds what docs/architecture.md
says it holds: ``small.toml`` (the page's ```toml block: a 35-pixel tile, two
training steps) and ``out/``, a ``doefab run --out out --config small.toml
--formats ply`` of it, made once. A block preceded by ``<!-- doc-test: skip ... -->``
does not run (say why in the comment).
"""

import contextlib
import re
import shutil
from pathlib import Path

import pytest

from doe.infra.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
# The architecture page and the command pages; each must show its stage from Python.
PAGES = (
    "architecture.md",
    "design.md",
    "learn.md",
    "retrieve.md",
    "fab.md",
    "tolerance.md",
    "mesh.md",
    "verify.md",
    "depth.md",
    "camera.md",
)
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.M | re.S)
SKIP = re.compile(r"<!--\s*doc-test:\s*skip\b[^>]*-->\s*$")


def blocks(page, language):
    """Return (line, code, skipped) of each fenced block of ``language`` in a page."""
    text = (DOCS / page).read_text()
    found = []
    for match in FENCE.finditer(text):
        if match.group(1) != language:
            continue
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        line = text.count("\n", 0, match.start()) + 2  # the block's first line of code
        found.append((line, match.group(2), bool(SKIP.search(before))))
    return found


EXAMPLES = [
    pytest.param(page, line, code, id=f"{page}:{line}")
    for page in PAGES
    for line, code, skipped in blocks(page, "python")
    if not skipped
]


@pytest.mark.parametrize("page", PAGES)
def test_each_page_shows_its_stage_from_python(page):
    text = (DOCS / page).read_text()
    assert re.search(r"^## From Python\b", text, re.M), f"docs/{page}: no '## From Python'"
    assert any(not skipped for _, _, skipped in blocks(page, "python")), (
        f"docs/{page}: no Python example that runs"
    )


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A folder with small.toml and out/, a finished run of it."""
    root = tmp_path_factory.mktemp("lab")
    (toml,) = [code for _, code, _ in blocks("architecture.md", "toml")]
    (root / "small.toml").write_text(toml)
    with contextlib.chdir(root):
        code = main(["run", "--out", "out", "--config", "small.toml", "--formats", "ply"])
    assert code == 0
    return root


@pytest.mark.parametrize("page, line, code", EXAMPLES)
def test_example_runs(lab, tmp_path, monkeypatch, page, line, code):
    work = tmp_path / "lab"
    shutil.copytree(lab, work)
    monkeypatch.chdir(work)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # padded so that a traceback gives the page's own line numbers
    source = compile("\n" * (line - 1) + code, str(DOCS / page), "exec")
    exec(source, {"__name__": "__doc_example__"})
