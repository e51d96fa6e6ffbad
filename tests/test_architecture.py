"""Architecture: doe/fab/layouts never import torch; only psf_learn may."""

import ast
import pathlib
import subprocess
import sys

import numpy as np

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
