"""Contract readers and the staged (all-or-nothing) output folder."""

import hashlib
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from doe.infra import interrupts
from doe.infra.cli import main
from doe.infra.errors import InputError
from doe.infra.files import (
    atomic_write_bytes,
    check_psf,
    read_json,
    read_levels,
    read_psf,
    save_npy,
    sha256_file,
    staged_output,
    write_json,
)


def test_staged_output_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError), staged_output(out) as stage:
        (stage / "a.txt").write_text("half")
        raise RuntimeError("killed")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_staging_folders_of_processes_gone_are_removed_by_the_next_run(tmp_path):
    # a run killed outright (SIGKILL, power cut) cannot clean up: its .out.staging-*
    # stayed beside --out for good. A live process's, another host's (whose processes
    # cannot be seen from here) and another output's stay.
    import re
    import socket

    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    host = re.sub(r"[^A-Za-z0-9]", "_", socket.gethostname())
    gone = tmp_path / f".out.staging-{host}-{dead}-x1"
    kept = [
        tmp_path / f".out.staging-{host}-{os.getpid()}-x2",
        tmp_path / f".out.staging-elsewhere-{dead}-x3",
        tmp_path / f".out2.staging-{host}-{dead}-x4",
    ]
    for folder in (gone, *kept):
        folder.mkdir()
        (folder / "mask.gds").write_text("half")
    with staged_output(tmp_path / "out", names=["a.txt"]) as stage:
        assert stage.name.startswith(f".out.staging-{host}-{os.getpid()}-")
        (stage / "a.txt").write_text("new")
    assert not gone.exists() and all(folder.exists() for folder in kept)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", *(k.name for k in kept)])


def test_staged_output_moves_files_and_refuses_overwrite(tmp_path):
    out = tmp_path / "out"
    with staged_output(out) as stage:
        (stage / "a.txt").write_text("one")
    assert (out / "a.txt").read_text() == "one"
    with pytest.raises(InputError, match="--force"), staged_output(out) as stage:
        (stage / "a.txt").write_text("two")
    assert (out / "a.txt").read_text() == "one"
    with staged_output(out, force=True) as stage:
        (stage / "a.txt").write_text("two")
    assert (out / "a.txt").read_text() == "two"


def test_staged_output_removes_stale_files_only_with_force_and_only_inside(tmp_path):
    out = tmp_path / "out"
    (out / "sub").mkdir(parents=True)
    for name in ("old.txt", "sub/old.txt", "keep.txt"):
        (out / name).write_text("old")
    (tmp_path / "outside.txt").write_text("not ours")
    stale = ["old.txt", "sub/old.txt", "new.txt", "../outside.txt", "sub"]
    with staged_output(out, stale=stale) as stage:
        (stage / "new.txt").write_text("new")
    assert (out / "old.txt").exists()  # without --force nothing is removed
    with staged_output(out, force=True, stale=stale) as stage:
        (stage / "new.txt").write_text("newer")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt", "new.txt"]
    assert (out / "new.txt").read_text() == "newer" and (tmp_path / "outside.txt").exists()


def test_an_interrupt_during_publishing_completes_the_package_first(tmp_path, monkeypatch):
    # Stopped between two moves, --force over an older package left it half old.
    import doe.infra.files

    out = tmp_path / "out"
    out.mkdir()
    for name in "abc":
        (out / name).write_text("old")
    real, moved = os.replace, []

    def replace(src, dst):
        real(src, dst)
        moved.append(dst)
        if len(moved) == 1:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs here

    monkeypatch.setattr(doe.infra.files.os, "replace", replace)
    with interrupts.handled(), pytest.raises(KeyboardInterrupt):
        with staged_output(out, force=True) as stage:
            for name in "abc":
                (stage / name).write_text("new")
    assert [(out / n).read_text() for n in "abc"] == ["new"] * 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging folder


def test_an_interrupt_in_nested_deferred_blocks_waits_for_the_outermost():
    # deferred() counts its depth: the end of an inner block must not raise the
    # signal while the outer block (a package half moved into place) still runs.
    done = []
    with interrupts.handled(), pytest.raises(KeyboardInterrupt):
        with interrupts.deferred():
            with interrupts.deferred():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # the handler runs here, and only records it
            done.append("inner")
            done.append("outer")
    assert done == ["inner", "outer"]


def test_a_swallowed_interrupt_publishes_nothing_and_exits_130(tmp_path, monkeypatch, capsys):
    # nlopt and matplotlib can swallow the KeyboardInterrupt: retrieve then finished,
    # exit 0, with a design the seed does not give.
    import doe.figures

    real = doe.figures.save_retrieval_figure

    def swallowing(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        except KeyboardInterrupt:
            pass
        return real(*args, **kwargs)

    monkeypatch.setattr(doe.figures, "save_retrieval_figure", swallowing)
    psf = tmp_path / "psf.npy"
    np.save(psf, np.full((3, 3), 1 / 9))
    out = tmp_path / "out"
    assert main(["retrieve", str(psf), "--out", str(out), "--tile-pixels", "15"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["psf.npy"]


@pytest.mark.parametrize("error, code", [(ZeroDivisionError, 3), (MemoryError, 2)])
def test_a_bug_exits_3_never_1_which_means_a_failed_check(
    tmp_path, monkeypatch, capsys, error, code
):
    # An uncaught exception exits 1, which for verify means "the plate fails".
    import doe.figures

    def broken(*args, **kwargs):
        raise error()

    monkeypatch.setattr(doe.figures, "save_retrieval_figure", broken)
    psf = tmp_path / "psf.npy"
    np.save(psf, np.full((3, 3), 1 / 9))
    assert (
        main(["retrieve", str(psf), "--out", str(tmp_path / "out"), "--tile-pixels", "15"]) == code
    )
    err = capsys.readouterr().err
    assert ("internal error" in err and "Traceback" in err) if code == 3 else "out of memory" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["psf.npy"]


def test_an_out_folder_on_another_file_system_is_written(tmp_path):
    # Staged beside a mount point or a link to another file system (a container's bind
    # mount), every command failed: "Invalid cross-device link".
    shm = Path("/dev/shm")
    if not shm.is_dir() or os.stat(shm).st_dev == os.stat(tmp_path).st_dev:
        pytest.skip("needs /dev/shm on another file system than the test folder")
    target = Path(tempfile.mkdtemp(dir=shm))
    try:
        (tmp_path / "out").symlink_to(target)
        with staged_output(tmp_path / "out") as stage:
            (stage / "a.txt").write_text("made")
        assert (target / "a.txt").read_text() == "made"
        assert sorted(p.name for p in target.iterdir()) == ["a.txt"]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    finally:
        shutil.rmtree(target)


def test_previous_files_reads_the_record_and_ignores_what_it_cannot(tmp_path):
    from doe.infra.files import previous_files

    record = tmp_path / "report.json"

    def files(report):
        return report["files"]

    record.write_text('{"files": {"tile.ply": 1, "tile.stl": 2}}')
    assert previous_files(record, files) == ["tile.ply", "tile.stl"]
    record.write_text('{"files": "ab"}')  # a hand-edited record: not a list of names
    assert previous_files(record, files) == []
    record.write_text("{not json")
    assert previous_files(record, files) == []
    assert previous_files(tmp_path / "missing.json", files) == []


def test_read_psf_normalises_within_tolerance_only(tmp_path):
    psf = np.zeros((3, 3))
    psf[1, 1] = 1 + 1e-9
    save_npy(tmp_path / "ok.npy", psf)
    assert read_psf(tmp_path / "ok.npy").sum() == pytest.approx(1, abs=1e-15)
    save_npy(tmp_path / "bad.npy", psf * 2)
    with pytest.raises(InputError, match="sum to 1"):
        read_psf(tmp_path / "bad.npy")


def test_a_psf_is_checked_and_normalised_in_float64_and_c_order(tmp_path):
    # float16 summed 1.0004 to exactly 1: retrieve passed it and wrote a target that
    # fab then refused; a Fortran-ordered copy gave another design for the same values.
    psf = np.random.default_rng(0).random((11, 11))
    psf /= psf.sum()
    with pytest.raises(InputError, match=r"must be float64 \(or float32\), got float16"):
        check_psf((psf * 1.0004).astype(np.float16), "f16.npy")
    fortran = check_psf(np.asfortranarray(psf), "f.npy")
    assert fortran.flags.c_contiguous and np.array_equal(fortran, check_psf(psf, "c.npy"))
    single = check_psf(psf.astype(np.float32), "single.npy")
    assert single.dtype == np.float64 and single.sum() == pytest.approx(1, abs=1e-15)


def test_a_npy_header_claiming_terabytes_is_refused_plainly(tmp_path):
    path = tmp_path / "huge.npy"
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000001, 1000001), }"
    header = header.ljust(118) + "\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
                     + bytes(968))  # fmt: skip
    with pytest.raises(InputError, match="too large for memory"):
        read_psf(path)


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.full((4, 4), 8, np.uint8), "0..7"),
        (np.zeros((4, 5), np.uint8), "square"),
        (np.zeros((4, 4), np.int64), "uint8"),
    ],
)
def test_read_levels_refuses_contract_violations(tmp_path, array, message):
    save_npy(tmp_path / "levels.npy", array)
    with pytest.raises(InputError, match=message):
        read_levels(tmp_path / "levels.npy", 8)


def test_a_stage_folder_given_for_its_file_is_named_as_a_folder(tmp_path, capsys):
    # `retrieve out/learn` once said "not a readable .npy array ([Errno 21] ...)";
    # `fab out/learn` said only that levels.npy is missing.
    learn = tmp_path / "learn"
    learn.mkdir()
    np.save(learn / "psf.npy", np.full((3, 3), 1 / 9))
    with pytest.raises(InputError, match=r"is a folder, not a \.npy file \(it holds psf\.npy\)"):
        read_psf(learn)
    assert main(["fab", str(learn), "--out", str(tmp_path / "fab")]) == 2
    assert "levels.npy: no such file; fab takes the folder that doefab retrieve wrote" in (
        capsys.readouterr().err
    )


def test_write_json_is_strict_json_with_undefined_figures_as_null(tmp_path, read_strict_json):
    obj = {
        "corr": float("nan"),
        "inf": np.float64(np.inf),
        "n": np.int64(3),
        "a": np.array([0.5, np.nan]),
        "t": (1, 2.5),
        "nested": [{"x": np.float32(0.25)}],
    }
    path = tmp_path / "f.json"
    write_json(path, obj)
    # a strict reader: Python's NaN / Infinity tokens would raise here
    back = read_strict_json(path)
    assert back == {
        "corr": None,
        "inf": None,
        "n": 3,
        "a": [0.5, None],
        "t": [1, 2.5],
        "nested": [{"x": 0.25}],
    }


@pytest.mark.parametrize("text", ["[]", "3", '"levels"', "null"])
def test_json_that_is_not_an_object_is_refused(tmp_path, text, capsys):
    # A list as retrieval.json once crashed doefab fab with an AttributeError.
    bad = tmp_path / "retrieval.json"
    bad.write_text(text)
    with pytest.raises(InputError, match="JSON object"):
        read_json(bad)
    save_npy(tmp_path / "levels.npy", np.zeros((15, 15), np.uint8))
    out = tmp_path / "fab"
    assert main(["fab", str(tmp_path), "--out", str(out)]) == 2
    assert "retrieval.json" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("levels", ['"eight"', "8.5", "true", "[8]"])
def test_a_level_count_of_the_wrong_type_in_retrieval_json_exits_2(tmp_path, levels, capsys):
    # "eight" once ended in a ValueError traceback (exit 3) and 8.5 read as 8
    (tmp_path / "retrieval.json").write_text(f'{{"levels": {levels}}}')
    save_npy(tmp_path / "levels.npy", np.zeros((15, 15), np.uint8))
    out = tmp_path / "fab"
    assert main(["fab", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "retrieval.json: 'levels' must be a whole number" in err and not out.exists()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "no such file"),
        (b'{"levels": 8', "not readable JSON"),  # cut short
        (b'{"name": "\xb5"}', "not readable JSON"),  # Latin-1, not UTF-8
    ],
)
def test_a_missing_or_unreadable_json_file_is_named(tmp_path, content, message):
    path = tmp_path / "retrieval.json"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=message) as e:
        read_json(path)
    assert str(path) in str(e.value)


def test_empty_or_unwritable_out_exits_2(tmp_path, capsys, monkeypatch):
    # An empty --out (an unset $OUT) once wrote into the current folder; an
    # unwritable one ended in a FileNotFoundError traceback.
    monkeypatch.chdir(tmp_path)
    psf, psf11 = tmp_path / "psf.npy", tmp_path / "psf11.npy"  # the design's K is 11
    save_npy(psf, np.full((3, 3), 1 / 9))
    save_npy(psf11, np.full((11, 11), 1 / 121))
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    for command in (["retrieve", str(psf), "--tile-pixels", "7"], ["run", "--psf", str(psf11)]):
        for out in ("", str(blocker / "sub")):
            assert main([*command, "--out", out]) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and ("--out" in err if not out else out in err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "psf.npy", "psf11.npy"]


def test_closed_stdout_ends_quietly(tmp_path):
    # `doefab config show | head`: the reader goes away. Like a tool killed by SIGPIPE:
    # status 141 and nothing on stderr (this once read "error: file system: Broken pipe").
    proc = subprocess.Popen(
        [sys.executable, "-m", "doe", "config", "show"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=tmp_path,
    )
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait() == 141 and err == b""


def _psf(k):
    psf = np.random.default_rng(0).random((k, k))
    return psf / psf.sum()


def test_a_psf_of_even_size_is_refused():
    # K odd: element [K//2, K//2] is the optical axis; an even K has none.
    with pytest.raises(InputError, match="odd"):
        check_psf(_psf(10), "even.npy")


def test_a_psf_with_any_negative_value_is_refused():
    # "all values >= 0": a tiny negative is still a negative intensity.
    psf = _psf(5)
    psf[0, 0] = -1e-12
    with pytest.raises(InputError, match="negative"):
        check_psf(psf, "neg.npy")


def test_a_psf_sum_within_one_ppm_is_renormalised_and_beyond_it_refused():
    # "sum == 1": float32 rounding (~1e-7) is renormalised; a PSF off by more than
    # 1e-6 was not normalised and must not be rescaled silently.
    with pytest.raises(InputError, match="sum to 1"):
        check_psf(_psf(5) * (1 + 1e-4), "off.npy")
    assert check_psf((_psf(5) * (1 + 1e-7)), "ok.npy").sum() == pytest.approx(1, abs=1e-15)
    psf = np.full((5, 5), 1 / 25)
    out = check_psf(psf * (1 + 5e-7), "near.npy")
    assert abs(out.sum() - 1) < 1e-15
    with pytest.raises(InputError, match="sum to 1"):
        check_psf(psf * (1 + 3e-6), "off.npy")


def test_sha256_file_hashes_all_of_a_file_larger_than_one_read_block(tmp_path):
    # GDS files run to many MiB; sha256_file reads in 1 MiB blocks
    data = np.random.default_rng(0).bytes(3 * (1 << 20) + 12345)
    path = tmp_path / "big.gds"
    path.write_bytes(data)
    assert sha256_file(path) == hashlib.sha256(data).hexdigest()
    # a change in the last byte changes the hash
    path.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    assert sha256_file(path) != hashlib.sha256(data).hexdigest()


def test_write_json_sorts_keys_at_every_level(tmp_path):
    # "indented, key-sorted JSON (deterministic bytes)": the same content in any
    # insertion order gives the same bytes
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    write_json(a, {"zeta": 1, "alpha": {"y": 2, "b": 3}})
    write_json(b, {"alpha": {"b": 3, "y": 2}, "zeta": 1})
    assert a.read_bytes() == b.read_bytes()
    text = a.read_text()
    assert text.index('"alpha"') < text.index('"zeta"')
    assert text.index('"b"') < text.index('"y"')


def test_a_failed_atomic_write_leaves_the_old_file_and_no_temporary_one(tmp_path):
    path = tmp_path / "x.bin"
    path.write_bytes(b"old")
    with pytest.raises(TypeError):
        atomic_write_bytes(path, "text, not bytes")
    assert path.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [path]


def test_a_file_that_cannot_be_published_is_named_as_the_output(tmp_path):
    # A folder where an output file goes (with --force, which skips the overwrite
    # check): the error names out/a.txt, not the staging file that vanishes with it.
    out = tmp_path / "out"
    (out / "a.txt").mkdir(parents=True)
    (out / "a.txt" / "lab.txt").write_text("the lab's")
    with pytest.raises(OSError) as e, staged_output(out, force=True) as stage:
        (stage / "a.txt").write_text("new")
    assert e.value.filename == str(out / "a.txt")
    assert (out / "a.txt" / "lab.txt").read_text() == "the lab's"
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]  # no staging folder left


def test_json_writes_paths_as_text(tmp_path, read_strict_json):
    write_json(tmp_path / "p.json", {"file": tmp_path / "levels.npy"})
    assert read_strict_json(tmp_path / "p.json") == {"file": str(tmp_path / "levels.npy")}


def test_handlers_are_installed_only_in_the_main_thread():
    import threading

    before = signal.getsignal(signal.SIGINT)
    ran = []

    def block():
        with interrupts.handled():  # signal.signal would raise ValueError here
            ran.append(signal.getsignal(signal.SIGINT))

    worker = threading.Thread(target=block)
    worker.start()
    worker.join()
    assert ran == [before]
    with interrupts.handled():
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before


def test_atomic_writes_get_the_usual_file_mode(tmp_path):
    # mkstemp makes 0600; a package file must be readable as any other file (0666 & ~umask)
    umask = os.umask(0)
    os.umask(umask)
    atomic_write_bytes(tmp_path / "x.bin", b"abc")
    write_json(tmp_path / "y.json", {"a": 1})
    for name in ("x.bin", "y.json"):
        mode = stat.S_IMODE((tmp_path / name).stat().st_mode)
        assert mode == 0o666 & ~umask
