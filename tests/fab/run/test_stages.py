"""fab.run.stages.run_pipeline called directly, with stand-in stages (fast)."""

import ast
import json
import pathlib

import numpy as np
import pytest

from doe.infra.errors import InputError
from fab.run.stages import RunResult, run_pipeline

ROOT = pathlib.Path(__file__).resolve().parents[3]


@pytest.fixture
def psf(tmp_path):
    path = tmp_path / "psf.npy"
    np.save(path, np.full((11, 11), 1 / 121))  # the default design's 11 x 11 kernel
    return path


class Stages:
    """Stand-ins for the doefab commands: each writes a file or two into its --out."""

    def __init__(self, fail=None):
        self.calls, self.fail = [], fail

    def __call__(self, argv):
        self.calls.append(argv)
        if argv[0] == self.fail:
            return 1
        out = pathlib.Path(argv[argv.index("--out") + 1])
        if argv[0] == "retrieve":
            np.save(out / "levels.npy", np.zeros((4, 4), np.uint8))
            np.save(out / "target_psf.npy", np.full((3, 3), 1 / 9))
            (out / "retrieval.json").write_text(json.dumps({"levels": 8, "seconds": 1.5}))
        else:
            (out / f"{argv[0]}.txt").write_text(argv[0])
        return 0


def test_run_pipeline_runs_each_stage_through_invoke_and_writes_the_summaries(tmp_path, psf):
    out, stages, lines = tmp_path / "run", Stages(), []
    result = run_pipeline(out, invoke=stages, psf=psf, formats="none", log=lines.append)
    assert isinstance(result, RunResult) and result.exit_code == 0
    assert result.stages == result.ran == ("retrieve", "fab") and result.skipped == ()
    assert [argv[0] for argv in stages.calls] == ["retrieve", "fab"]
    assert stages.calls[0] == ["retrieve", str(psf), "--seed", "0", "--out",
                               str(out / ".retrieve.new"), "--force"]  # fmt: skip
    assert result.index == out / "index.html" and result.index.is_file()
    assert lines[0] == f"[1/2] retrieve: doefab retrieve {psf} --seed 0"
    assert lines[1].startswith("[1/2] retrieve: done in ") and lines[1].endswith(
        f" s -> {out / 'retrieve'}"
    )
    assert lines[2] == f"[2/2] fab: doefab fab {out / 'retrieve'}" and len(lines) == 4
    # the stage's own timing moves to timings.json, leaving its report reproducible
    assert json.loads((out / "retrieve" / "retrieval.json").read_text())["seconds"] is None
    timings = json.loads((out / "timings.json").read_text())
    assert timings["seconds_reported_by_stages"]["retrieve"] == {"retrieval.json": 1.5}
    listed = [f["path"] for f in json.loads((out / "manifest.json").read_text())["files"]]
    assert listed == ["fab/fab.txt", "index.html", "retrieve/levels.npy",
                      "retrieve/retrieval.json", "retrieve/target_psf.npy"]  # fmt: skip
    # again: nothing to do
    lines.clear()
    again = run_pipeline(out, invoke=stages, psf=psf, formats="none", log=lines.append)
    assert again.exit_code == 0 and again.ran == () and again.skipped == ("retrieve", "fab")
    assert lines == ["[1/2] retrieve: up to date, skipped", "[2/2] fab: up to date, skipped"]
    assert len(stages.calls) == 2


def test_a_failing_stage_stops_the_run_with_its_exit_code(tmp_path, psf):
    out, lines = tmp_path / "run", []
    stages = Stages(fail="fab")
    result = run_pipeline(out, invoke=stages, psf=psf, formats="none", log=lines.append)
    assert result.exit_code == 1 and result.failed == "fab" and result.index is None
    assert result.ran == ("retrieve", "fab")
    assert lines[-1] == "doefab run: stage fab failed (exit 1)"
    assert not (out / "index.html").exists() and not (out / "manifest.json").exists()
    assert (out / "retrieve" / "levels.npy").is_file() and not (out / "fab").exists()


def test_bad_values_raise_before_any_stage(tmp_path, psf):
    stages = Stages()
    for values, flag in (
        ({"minutes": float("nan")}, "--minutes"),
        ({"seed": -1}, "--seed"),
        ({"formats": "ply,obj"}, "--formats"),
    ):
        with pytest.raises(InputError, match=flag):
            run_pipeline(tmp_path / "run", invoke=stages, psf=psf, **values)
    with pytest.raises(InputError, match=r"none\.npy"):
        run_pipeline(tmp_path / "run", invoke=stages, psf=tmp_path / "none.npy")
    assert not stages.calls and not (tmp_path / "run").exists()


def test_folders_of_stages_not_planned_are_reported_and_left_out(tmp_path, psf):
    out, lines = tmp_path / "run", []
    run_pipeline(out, invoke=Stages(), psf=psf, formats="none")
    (out / "mesh").mkdir()  # as an earlier run with meshes left it
    (out / "mesh" / "tile.ply").write_text("an earlier tile")
    result = run_pipeline(out, invoke=Stages(), psf=psf, formats="none", log=lines.append)
    assert result.left_out == (out / "mesh",)
    assert lines[-1] == (
        f"doefab run: {out / 'mesh'} is from an earlier run and not part of this one; "
        "manifest.json and index.html leave it out"
    )
    listed = [f["path"] for f in json.loads((out / "manifest.json").read_text())["files"]]
    assert not [p for p in listed if p.startswith("mesh/")]
    assert (out / "mesh" / "tile.ply").is_file()


def test_the_run_stage_does_not_import_the_dispatcher():
    # The dispatcher loads the run command, which must not import it back (a circle):
    # it hands itself to the command as args.invoke.
    for rel in ("fab/run/stages.py", "fab/run/pipeline.py", "fab/commands/run.py"):
        tree = ast.parse((ROOT / rel).read_text())
        imported = [
            node.module if isinstance(node, ast.ImportFrom) else alias.name
            for node in ast.walk(tree)
            if isinstance(node, ast.Import | ast.ImportFrom)
            for alias in node.names
        ]
        assert not [m for m in imported if m and m.startswith("doe.infra.cli")], rel
        assert not [m for m in imported if m and ".commands" in m], rel
