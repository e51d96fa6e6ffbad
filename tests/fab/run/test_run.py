"""``doefab run`` end to end on a small design: package, skip on rerun, reproducible, resumable."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from doe.infra.cli import main
from fab.run.pipeline import sha256_file

pytestmark = pytest.mark.slow

SMALL = """
name = "small"
[fabrication]
feature_size_um = 20.0     # N = 43 pixels of 20.31 um (873.3 um / 20 um = 43.67): a fast tile
[learning]
steps = 12
"""
FORMATS = "ply,glb,3mf,stl,step"


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "small.toml"
    path.write_text(SMALL)
    return path


def run(config, out, *extra):
    return main(["run", "--config", str(config), "--out", str(out), "--formats", FORMATS, *extra])


@pytest.fixture(scope="module")
def finished(config, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "out"
    assert run(config, out) == 0
    return out


def test_run_writes_the_whole_package(finished):
    for rel in (
        "learn/psf.npy",
        "retrieve/levels.npy",
        "fab/mask.gds",
        "fab/fab_manifest.json",
        "fab/fab_report.html",
        "mesh/tile.ply",
        "mesh/tile.step",
        "index.html",
    ):
        assert (finished / rel).is_file(), rel
    assert not list(finished.glob("*/.*"))  # no bookkeeping left inside the packages
    manifest = json.loads((finished / "manifest.json").read_text())
    listed = {f["path"]: f["sha256"] for f in manifest["files"]}
    assert "index.html" in listed and "fab/mask.gds" in listed
    for rel, digest in listed.items():
        assert sha256_file(finished / rel) == digest, rel
    assert manifest["design"]["derived"]["tile_pixels"] == 43
    assert manifest["seeds"] == {"learn": 0, "retrieve": 0}
    assert manifest["versions"]["numpy"]
    index = (finished / "index.html").read_text()
    assert "fab/fab_report.html" in index and "retrieve/retrieval.png" in index
    met = json.loads((finished / "retrieve/retrieval.json").read_text())["goals"]["met"]
    verdict = "yes" if met else "NO: see retrieve/retrieval.json"
    assert f"<td>correlation and rmse goals met</td><td>{verdict}</td>" in index
    # what the plate buys, in both conventions; the training batch's PSNR is not a headline
    held = json.loads((finished / "learn/learn.json").read_text())["heldout"]
    model, base, gain = held["model"], held["no_plate"], held["plate_gain_db"]
    shown = f"{model['psnr_y']:.2f} / {base['psnr_y']:.2f} / {gain['psnr_y']:+.2f}</td>"
    assert "PSNR-Y (MATLAB Y 16-235" in index and shown in index
    assert "training PSNR" not in index and "training-batch" not in index


def test_rerun_skips_every_stage_and_changes_nothing(config, finished, capsys):
    before = (finished / "manifest.json").read_bytes()
    capsys.readouterr()
    assert run(config, finished) == 0
    err = capsys.readouterr().err
    assert err.count("up to date, skipped") == 4, err
    assert (finished / "manifest.json").read_bytes() == before


def test_a_second_run_gives_byte_identical_outputs(config, finished, tmp_path, capsys):
    out = tmp_path / "again"
    assert run(config, out) == 0
    assert (out / "manifest.json").read_bytes() == (finished / "manifest.json").read_bytes()
    # Each stage reports its staging folder; the run then names where the files are.
    err = capsys.readouterr().err
    for i, name in enumerate(("learn", "retrieve", "fab", "mesh"), 1):
        assert f"[{i}/4] {name}: done in " in err and f"-> {out / name}\n" in err


# `doefab` in a subprocess, learn scoring on the tests' small held-back image as in
# this process (tests/conftest.py), so that its learn.json is the in-process run's
DOEFAB_SMALL_HELD_OUT = (
    f"import sys; sys.path.insert(0, {str(Path(__file__).parents[2])!r}); "
    "import conftest, psf_learn.images as images; "
    "images.held_out_images = conftest._small_held_out; "
    "from doe.infra.cli import main; sys.exit(main(sys.argv[1:]))"
)


def test_killed_run_resumes_to_the_same_outputs(config, finished, tmp_path):
    out = tmp_path / "killed"
    cmd = [
        sys.executable,
        "-c",
        DOEFAB_SMALL_HELD_OUT,
        "run",
        "--config",
        str(config),
        "--out",
        str(out),
        "--formats",
        FORMATS,
    ]
    proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while not (out / "retrieve").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)  # part-way: learn and retrieve done, fab running
    proc.wait()
    assert not (out / "manifest.json").exists()
    assert run(config, out) == 0
    assert (out / "manifest.json").read_bytes() == (finished / "manifest.json").read_bytes()


def test_edited_output_is_not_overwritten(config, finished, tmp_path, capsys):
    report = finished / "fab" / "fab_report.md"
    original = report.read_bytes()
    try:
        report.write_text("my notes")
        capsys.readouterr()
        assert run(config, finished) == 2
        assert "fab_report.md" in capsys.readouterr().err
        assert report.read_text() == "my notes"
    finally:
        report.write_bytes(original)


def test_formats_none_leaves_the_mesh_stage_out(config, finished, tmp_path, capsys):
    # A fine-pitch tile can be too large to mesh; the rest of the run must still finish.
    out = tmp_path / "out"
    psf = finished / "learn" / "psf.npy"
    argv = ["run", "--config", str(config), "--out", str(out), "--psf", str(psf)]
    assert main([*argv, "--formats", "none"]) == 0
    err = capsys.readouterr().err
    assert "[2/2] fab: done" in err and "mesh:" not in err  # retrieve and fab only
    assert (out / "fab" / "mask.gds").is_file() and (out / "index.html").is_file()
    assert not (out / "mesh").exists()
    listed = [f["path"] for f in json.loads((out / "manifest.json").read_text())["files"]]
    assert "fab/mask.gds" in listed and not [p for p in listed if p.startswith("mesh/")]
    for name in ("mask.gds", "levels.npy"):
        assert sha256_file(out / "fab" / name) == sha256_file(finished / "fab" / name)


def test_folders_of_stages_left_out_are_not_listed_as_products(config, finished, tmp_path, capsys):
    # A run with --psf and --formats none over an earlier full run must not pass the
    # earlier learn/ and mesh/ (made from another tile) off as its own products.
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    capsys.readouterr()
    psf = out / "learn" / "psf.npy"
    argv = ["run", "--config", str(config), "--out", str(out), "--psf", str(psf), "--seed", "3"]
    assert main([*argv, "--formats", "none"]) == 0
    err = capsys.readouterr().err
    assert f"{out / 'learn'} is from an earlier run" in err and f"{out / 'mesh'} is from" in err
    listed = [f["path"] for f in json.loads((out / "manifest.json").read_text())["files"]]
    assert "fab/mask.gds" in listed and "index.html" in listed
    assert not [p for p in listed if p.startswith(("learn/", "mesh/"))]
    index = (out / "index.html").read_text()
    assert "mesh/" not in index and "learn/" not in index and "training PSNR" not in index
    assert (out / "mesh" / "tile.ply").is_file()  # left in place, not deleted


def psf_run(config, finished, out, *extra):
    """A quick run (retrieve and fab only) on the finished run's PSF."""
    psf = str(finished / "learn" / "psf.npy")
    argv = ["run", "--config", str(config), "--out", str(out), "--psf", psf, "--formats", "none"]
    return main([*argv, *extra])


def test_a_design_file_edited_without_changing_a_value_redoes_nothing(
    config, finished, tmp_path, capsys
):
    # The stages were keyed on the file's bytes: a comment re-ran minutes of training.
    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    moved = tmp_path / "elsewhere" / "same.toml"
    moved.parent.mkdir()
    moved.write_text(
        '# the same design, reordered\nname = "small"\n[learning]\nsteps = 12  # quick\n'
        "[fabrication]\nfeature_size_um = 20.0\n"
    )
    capsys.readouterr()
    assert psf_run(moved, finished, out) == 0
    err = capsys.readouterr().err
    assert err.count("up to date, skipped") == 2, err
    moved.write_text(moved.read_text().replace('name = "small"', 'name = "renamed"'))
    assert psf_run(moved, finished, out) == 0
    err = capsys.readouterr().err
    assert "up to date" not in err and f"--config {moved}" in err, err
    assert json.loads((out / "fab" / "fab_manifest.json").read_text())["design_name"] == "renamed"


def test_the_labs_own_files_are_kept_and_not_listed(config, finished, tmp_path):
    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    own = [out / "notes.txt", out / "fab" / "my_notes.txt", out / "fab" / "sub" / "photo.png"]
    # hidden ones, an empty folder and a link to a folder too: a redone stage removed them
    own += [out / "fab" / ".notes", out / "fab" / ".git" / "HEAD"]
    for path in own:
        path.parent.mkdir(exist_ok=True)
        path.write_text("the lab's")
    (out / "fab" / "empty").mkdir()
    (tmp_path / "captures").mkdir()
    (out / "fab" / "captures").symlink_to(tmp_path / "captures")
    for extra in ((), ("--seed", "5"), ("--force",)):  # skipped, redone, forced
        assert psf_run(config, finished, out, *extra) == 0, extra
        assert all(path.read_text() == "the lab's" for path in own), extra
        assert (out / "fab" / "empty").is_dir() and (out / "fab" / "captures").is_symlink()
        listed = [f["path"] for f in json.loads((out / "manifest.json").read_text())["files"]]
        assert "fab/mask.gds" in listed
        assert not {"notes.txt", "fab/my_notes.txt", "fab/sub/photo.png"} & set(listed)


def test_a_labs_file_named_as_a_new_output_is_refused_without_force(config, finished, tmp_path):
    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    (out / "fab" / "mask.gds").unlink()
    (out / "fab" / "mask.gds").write_text("the lab's")  # unrecorded once the record goes
    state = json.loads((out / "run_state.json").read_text())
    del state["fab"]["files"]["mask.gds"]
    (out / "run_state.json").write_text(json.dumps(state))
    assert psf_run(config, finished, out, "--seed", "5") == 2
    assert (out / "fab" / "mask.gds").read_text() == "the lab's"
    assert psf_run(config, finished, out, "--seed", "5", "--force") == 0
    assert (out / "fab" / "mask.gds").read_bytes().startswith(b"\x00")  # a GDS again


def test_an_edited_output_stops_the_run_before_any_stage(config, finished, tmp_path, capsys):
    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    levels = (out / "retrieve" / "levels.npy").read_bytes()
    (out / "fab" / "fab_report.md").write_text("my notes")
    capsys.readouterr()
    assert psf_run(config, finished, out, "--seed", "5") == 2  # retrieve would redo first
    assert "fab_report.md" in capsys.readouterr().err
    assert (out / "retrieve" / "levels.npy").read_bytes() == levels
    assert (out / "index.html").is_file()  # nothing ran: the front page still holds


def test_a_run_stopped_part_way_leaves_no_front_page_of_the_old_stages(
    config, finished, tmp_path, monkeypatch
):
    import doe.infra.cli

    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    real = doe.infra.cli.main

    def fab_fails(argv):
        return 1 if argv[0] == "fab" else real(argv)

    monkeypatch.setattr(doe.infra.cli, "main", fab_fails)
    assert psf_run(config, finished, out, "--seed", "5") == 1  # retrieve redone, fab failed
    # retrieve/ now holds the new tile, fab/ the old package: no summary may call them one run
    assert not (out / "index.html").exists() and not (out / "manifest.json").exists()
    monkeypatch.setattr(doe.infra.cli, "main", real)
    assert psf_run(config, finished, out, "--seed", "5") == 0
    assert (out / "index.html").is_file() and (out / "manifest.json").is_file()


def test_staging_folders_of_a_killed_stage_are_removed(config, finished, tmp_path, capsys):
    out = tmp_path / "out"
    assert psf_run(config, finished, out) == 0
    leftover = out / "..fab.new.staging-abc123"
    leftover.mkdir()
    (leftover / "mask.gds").write_text("half")
    assert psf_run(config, finished, out, "--seed", "5") == 0
    assert not leftover.exists()
    # and the unfinished folder of a stage a stopped --force run was redoing, once a run
    # finds that stage up to date (no later run would remove it)
    unfinished = out / ".fab.new"
    unfinished.mkdir()
    (unfinished / ".stage_key").write_text("the stopped run's")
    capsys.readouterr()
    assert psf_run(config, finished, out, "--seed", "5") == 0
    assert "fab: up to date, skipped" in capsys.readouterr().err
    assert not unfinished.exists()


def test_index_labels_the_level_count_of_the_retrieval(tmp_path):
    from doe.design import load_design
    from fab.run.summary import write_index

    (tmp_path / "retrieve").mkdir()
    quantised = {"correlation": 0.99, "rmse": 0.01, "efficiency": 0.7}
    report = {"levels": 4, "quantised": quantised}
    (tmp_path / "retrieve" / "retrieval.json").write_text(json.dumps(report))
    write_index(tmp_path, load_design(None), ["retrieve"])
    index = (tmp_path / "index.html").read_text()
    assert "efficiency (4 levels)</td><td>0.7<" in index and "8 levels" not in index


def test_the_manifest_records_a_package_that_is_not_installed_as_none(monkeypatch):
    from importlib import metadata

    from fab.run.summary import PACKAGES, package_versions

    installed = metadata.version

    def without_trimesh(name):
        if name == "trimesh":
            raise metadata.PackageNotFoundError(name)
        return installed(name)

    monkeypatch.setattr(metadata, "version", without_trimesh)
    versions = package_versions()
    assert versions["trimesh"] is None and versions["numpy"] == installed("numpy")
    assert set(versions) == {"python", *PACKAGES}


def test_index_never_shows_a_missed_goal_rounded_onto_the_goal(tmp_path):
    # 0.99989996 was shown as 0.9999 beside "goals met: NO"
    from doe.design import load_design
    from fab.run.summary import write_index

    (tmp_path / "retrieve").mkdir()
    quantised = {"correlation": 0.99989996, "rmse": 0.0050004, "efficiency": 0.7}
    plate = {"goals_met": False}
    report = {"levels": 8, "quantised": quantised, "goals": {"met": False}, "square_pixels": plate}
    (tmp_path / "retrieve" / "retrieval.json").write_text(json.dumps(report))
    write_index(tmp_path, load_design(None), ["retrieve"])
    index = (tmp_path / "index.html").read_text()
    assert "correlation (8 levels)</td><td>0.99989996<" in index
    assert "rmse (8 levels)</td><td>0.0050004<" in index
    assert "as a plate of square pixels (their sinc^2 envelope)</td><td>NO: see retrieve/" in index


def test_a_second_run_in_the_same_folder_is_refused(config, finished, tmp_path, capsys):
    # Two runs shared the staging folders: the second failed with "cc/.learn.new/.stage_key:
    # No such file or directory", and the first could have moved a mix of both into place.
    from fab.run.pipeline import run_lock

    out = tmp_path / "out"
    out.mkdir()
    psf = str(finished / "learn" / "psf.npy")
    argv = ["run", "--config", str(config), "--out", str(out), "--psf", psf, "--formats", "none"]
    with run_lock(out):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert str(out) in err and f"(pid {os.getpid()})" in err and "another doefab run" in err
        assert [p.name for p in out.iterdir()] == [".doefab_run.lock"]
    assert main(argv) == 0  # released at the end of the first run


def test_a_folder_that_cannot_be_locked_runs_with_a_warning(tmp_path, monkeypatch, capsys):
    # Some network file systems refuse flock (ENOLCK): the run goes on, unguarded.
    import errno
    import fcntl

    from fab.run.pipeline import run_lock

    def no_locks(*_):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with run_lock(tmp_path):
        ran = True
    assert ran and "cannot lock" in capsys.readouterr().err


def test_bad_inputs_exit_2(tmp_path, capsys):
    assert main(["run", "--out", str(tmp_path / "o"), "--minutes", "1e308"]) == 2
    assert "--minutes: must be at most 1e+06" in capsys.readouterr().err
    assert main(["run", "--out", str(tmp_path / "o"), "--psf", str(tmp_path / "none.npy")]) == 2
    assert "none.npy" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    for text in ("[fabrication]\nlevels = 3\n", "[learning]\nphotons_per_pixel = 1e300\n"):
        bad.write_text(text)
        assert main(["run", "--config", str(bad), "--out", str(tmp_path / "o2")]) == 2
        assert "bad.toml" in capsys.readouterr().err
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "thesis.tex").write_text("precious")
    assert main(["run", "--out", str(stranger), "--psf", str(tmp_path / "none.npy")]) == 2
    assert (stranger / "thesis.tex").read_text() == "precious"
    # Bad values stop the run before its first stage, leaving nothing behind (a mesh
    # format typo once failed the last stage, after minutes of learning).
    for flag, value in (
        ("--seed", "-1"),
        ("--seed", str(2**63)),  # once a traceback from torch.manual_seed, after the checks
        ("--minutes", "nan"),
        ("--formats", "ply,obj"),
    ):
        fresh = tmp_path / f"o{flag}"
        assert main(["run", "--out", str(fresh), flag, value]) == 2
        assert flag in capsys.readouterr().err and not fresh.exists()
    # So does a PSF off the contract (it once left a locked run folder with an empty
    # staging folder behind), or a stage folder given for the PSF in it.
    np.save(tmp_path / "unnormalised.npy", np.full((3, 3), 1 / 3))
    # A PSF measured on a plate with a 75 um dot lattice is for another grid than
    # the default design's 37.5 um sub-pixels; it once failed only at the retrieve stage.
    measured = tmp_path / "measured"
    measured.mkdir()
    np.save(measured / "measured_psf.npy", np.full((3, 3), 1 / 9))
    (measured / "verify.json").write_text(json.dumps({"lattice_pitch_um": 75.0}))
    # A PSF of another size than the design's kernel: the manifest said K = 11 of a
    # 3 x 3 plate, and verify measured the wrong window (learn refuses it too).
    np.save(tmp_path / "small.npy", np.full((3, 3), 1 / 9))
    for psf, message in (
        ("unnormalised.npy", "must sum to 1"),
        (".", "is a folder"),
        ("measured/measured_psf.npy", "75 um dot lattice"),
        ("small.npy", "is 3 x 3, but the kernel of design 'sun2020' is 11 x 11"),
    ):
        fresh = tmp_path / f"o_{psf.replace('/', '_')}"
        assert main(["run", "--out", str(fresh), "--psf", str(tmp_path / psf)]) == 2
        assert message in capsys.readouterr().err and not fresh.exists()
    thick = tmp_path / "thick.toml"
    thick.write_text("[material]\nthickness_mm = 50\n")
    assert main(["run", "--config", str(thick), "--out", str(tmp_path / "o3")]) == 2
    assert "thickness_mm" in capsys.readouterr().err and not (tmp_path / "o3").exists()


def test_a_folder_of_other_files_or_an_unreadable_run_state_is_refused(
    tmp_path, capsys, monkeypatch
):
    import doe.infra.cli

    psf = tmp_path / "psf.npy"
    np.save(psf, np.full((11, 11), 1 / 121))  # the default design's 11 x 11 kernel
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "thesis.tex").write_text("precious")
    argv = ["run", "--psf", str(psf), "--formats", "none", "--out"]
    assert main([*argv, str(stranger)]) == 2
    assert f"{stranger}: is not empty and holds no doefab run; use --force" in (
        capsys.readouterr().err
    )
    assert sorted(p.name for p in stranger.iterdir()) == [".doefab_run.lock", "thesis.tex"]
    state = stranger / "run_state.json"
    state.write_text('{"retrieve": ')  # cut short (not by the run: it writes atomically)
    assert main([*argv, str(stranger)]) == 2
    err = capsys.readouterr().err
    assert f"{state}: unreadable run state" in err and "use --force to start over" in err
    # --force starts over: the run goes on to its first stage
    called = []
    monkeypatch.setattr(doe.infra.cli, "main", lambda argv: called.append(argv[0]) or 1)
    assert main([*argv, str(stranger), "--force"]) == 1
    assert called == ["retrieve"] and (stranger / "thesis.tex").read_text() == "precious"


def test_a_step_budget_learns_on_the_cpu(config, tmp_path):
    # Two CUDA trainings of the same steps differ (on an H100, PSFs 4e-4 apart), and so
    # would the plates of two runs: a step budget keeps the learn stage off the GPU.
    from doe.design import load_design
    from fab.run.stages import RunOptions, plan_stages

    design = load_design(str(config))
    for minutes, device in ((None, "cpu"), (1.0, None)):
        learn = plan_stages(tmp_path, design, RunOptions(minutes=minutes))[0]
        assert learn.name == "learn"
        argv = list(learn.argv)
        assert (argv[argv.index("--device") + 1] if "--device" in argv else None) == device
