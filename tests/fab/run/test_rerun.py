"""Re-runs redo only what changed: learn's own keys, ``--force STAGE``, ``--steps``."""

import json
import pathlib
import zlib

import numpy as np
import pytest

from doe.infra.cli import main
from doe.infra.errors import InputError
from fab.run.pipeline import sha256_file
from fab.run.stages import RunResult, run_pipeline

SMALL = """
name = "small"
[fabrication]
feature_size_um = 20.0     # N = 43 pixels: a fast tile
levels = {levels}
[learning]
steps = 12
photons_per_pixel = {photons}
"""


def design(tmp_path, levels=8, photons=1000.0, name="small.toml"):
    path = tmp_path / name
    path.write_text(SMALL.format(levels=levels, photons=photons))
    return path


class Stages:
    """Stand-ins for the doefab commands: each writes its stage's files into its --out.

    What each writes depends on its command line and the design it reads, as with
    the real ones.
    """

    def __init__(self):
        self.calls, self.argv = [], {}

    def __call__(self, argv):
        self.calls.append(argv[0])
        self.argv[argv[0]] = argv
        out = pathlib.Path(argv[argv.index("--out") + 1])
        config = argv[argv.index("--config") + 1] if "--config" in argv else None
        read = pathlib.Path(config).read_text() if config else ""
        if argv[0] == "learn":
            np.save(out / "psf.npy", np.full((11, 11), zlib.crc32(f"{argv}{read}".encode())))
        elif argv[0] == "retrieve":
            np.save(out / "levels.npy", np.zeros((4, 4), np.uint8))
            np.save(out / "target_psf.npy", np.full((3, 3), 1 / 9))
            (out / "design.toml").write_text(read)
        elif argv[0] == "fab":
            (out / "fab_manifest.json").write_text(json.dumps({"design": read}))
            np.save(out / "levels.npy", np.zeros((4, 4), np.uint8))
        else:
            (out / f"{argv[0]}.txt").write_text(argv[0])
        return 0


def rerun(out, config, stages, **options):
    return run_pipeline(out, invoke=stages, config=config, formats="ply", **options)


def test_a_change_of_levels_keeps_learn_and_redoes_the_rest(tmp_path):
    out, stages = tmp_path / "run", Stages()
    rerun(out, design(tmp_path), stages)
    assert stages.calls == ["learn", "retrieve", "fab", "mesh"]
    result = rerun(out, design(tmp_path, levels=4), stages)
    assert result.skipped == ("learn",) and result.ran == ("retrieve", "fab", "mesh")


def test_allowing_corner_contacts_keeps_learn_and_redoes_the_rest(tmp_path):
    out, stages, config = tmp_path / "run", Stages(), design(tmp_path)
    rerun(out, config, stages)
    config.write_text(
        config.read_text().replace("[fabrication]", "[fabrication]\nallow_corner_contacts = true")
    )
    result = rerun(out, config, stages)
    assert result.skipped == ("learn",) and result.ran == ("retrieve", "fab", "mesh")


def test_a_change_of_a_learning_key_redoes_learn_and_everything_after(tmp_path):
    out, stages = tmp_path / "run", Stages()
    rerun(out, design(tmp_path), stages)
    result = rerun(out, design(tmp_path, photons=500.0), stages)
    assert result.ran == ("learn", "retrieve", "fab", "mesh") and result.skipped == ()


def test_force_a_stage_redoes_it_and_those_after_it(tmp_path):
    out, stages = tmp_path / "run", Stages()
    config = design(tmp_path)
    rerun(out, config, stages)
    result = rerun(out, config, stages, force="fab")
    assert result.skipped == ("learn", "retrieve") and result.ran == ("fab", "mesh")
    # an edited output of a forced stage is overwritten; one before it still stops the run
    (out / "fab" / "fab_manifest.json").write_text('{"edited": true}')
    assert rerun(out, config, stages, force="fab").ran == ("fab", "mesh")
    (out / "retrieve" / "levels.npy").write_bytes(b"edited")
    with pytest.raises(InputError, match="edited since this run wrote it"):
        rerun(out, config, stages, force="fab")
    assert rerun(out, config, stages, force=True).ran == ("learn", "retrieve", "fab", "mesh")


def test_force_names_a_stage_of_the_run(tmp_path):
    config, stages = design(tmp_path), Stages()
    with pytest.raises(InputError, match="'etch' is no stage"):
        rerun(tmp_path / "a", config, stages, force="etch")
    with pytest.raises(InputError, match=r"mesh is not a stage of this run \(learn, retrieve"):
        run_pipeline(tmp_path / "b", invoke=stages, config=config, formats="none", force="mesh")
    assert stages.calls == []


def test_steps_is_a_learn_input(tmp_path):
    out, stages = tmp_path / "run", Stages()
    config = design(tmp_path)
    rerun(out, config, stages, steps=3)
    assert rerun(out, config, stages, steps=3).ran == ()
    stages.calls.clear()
    assert rerun(out, config, stages, steps=4).ran[0] == "learn"
    assert stages.argv["learn"][:3] == ["learn", "--steps", "4"]
    with pytest.raises(InputError, match="--steps"):
        rerun(out, config, stages, steps=0)
    with pytest.raises(InputError, match="not with --steps"):
        rerun(out, config, stages, steps=3, minutes=1.0)


def test_the_command_line_takes_force_stage_and_steps(tmp_path, monkeypatch, capsys):
    import fab.run.stages

    given = []

    def stand_in(out, **options):
        given.append(options)
        return RunResult(run_dir=out, exit_code=1, stages=())

    monkeypatch.setattr(fab.run.stages, "run_pipeline", stand_in)
    argv = ["run", "--out", str(tmp_path / "o")]
    for extra, force, steps in (
        ((), False, None),
        (("--force",), True, None),
        (("--force", "fab", "--steps", "7"), "fab", 7),
        (("--steps", "7", "--force"), True, 7),
    ):
        assert main([*argv, *extra]) == 1
        assert (given[-1]["force"], given[-1]["steps"]) == (force, steps)
    assert not any(options["no_baseline"] for options in given)
    assert main([*argv, "--no-baseline"]) == 1 and given[-1]["no_baseline"] is True
    for extra, why in (
        (("--force", "etch"), "invalid choice: 'etch'"),
        (("--steps", "2", "--minutes", "1"), "not allowed with argument"),
    ):
        with pytest.raises(SystemExit):
            main([*argv, *extra])
        assert why in capsys.readouterr().err


@pytest.mark.slow
def test_levels_change_keeps_the_learned_files_and_steps_are_recorded(tmp_path, capsys):
    out = tmp_path / "run"

    def run(config, *extra):
        argv = ["run", "--config", str(config), "--out", str(out), "--formats", "ply"]
        return main([*argv, "--steps", "3", *extra])

    assert run(design(tmp_path)) == 0
    learned = {p.name: sha256_file(p) for p in (out / "learn").iterdir()}
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / "learn").iterdir()}
    assert json.loads((out / "learn" / "learn.json").read_text())["steps"] == 3
    levels = (out / "retrieve" / "levels.npy").read_bytes()
    capsys.readouterr()
    assert run(design(tmp_path, levels=4)) == 0
    err = capsys.readouterr().err
    assert "[1/4] learn: up to date, skipped" in err
    for i, name in enumerate(("retrieve", "fab", "mesh"), 2):
        assert f"[{i}/4] {name}: done in " in err
    assert {p.name: sha256_file(p) for p in (out / "learn").iterdir()} == learned
    assert {p.name: p.stat().st_mtime_ns for p in (out / "learn").iterdir()} == mtimes
    assert (out / "retrieve" / "levels.npy").read_bytes() != levels
    assert json.loads((out / "retrieve" / "retrieval.json").read_text())["levels"] == 4
    capsys.readouterr()
    assert run(design(tmp_path, levels=4), "--force", "fab") == 0
    err = capsys.readouterr().err
    assert "learn: up to date" in err and "retrieve: up to date" in err
    assert "[3/4] fab: doefab fab" in err and "[4/4] mesh: doefab mesh" in err


def test_no_baseline_is_a_learn_input(tmp_path):
    # learn without the no-plate model writes another learn.json: the stage is redone
    out, stages = tmp_path / "run", Stages()
    config = design(tmp_path)
    rerun(out, config, stages)
    assert "--no-baseline" not in stages.argv["learn"]
    result = rerun(out, config, stages, no_baseline=True)
    assert result.ran[0] == "learn" and "--no-baseline" in stages.argv["learn"]
    assert rerun(out, config, stages, no_baseline=True).ran == ()
