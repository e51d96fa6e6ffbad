"""Stage bookkeeping of ``doefab run``: skip unchanged, redo changed, resume, never clobber."""

import pytest

from doe.infra.errors import InputError
from fab.run import pipeline
from fab.run.pipeline import Stage, check_overwrite, is_current, load_state, run_stage


class FakeDoefab:
    """Stands in for the doefab CLI: copies its input file, upper-cased, into --out."""

    def __init__(self, fail_on=None):
        self.calls = []
        self.fail_on = fail_on

    def __call__(self, argv):
        self.calls.append(argv[0])
        if argv[0] == self.fail_on:
            return 2
        src, out = argv[1], argv[argv.index("--out") + 1]
        with open(src) as f:
            text = f.read().upper()
        with open(f"{out}/{argv[0]}.txt", "w") as f:
            f.write(text)
        return 0


def stages(tmp_path):
    src = tmp_path / "input.txt"
    return [
        Stage("first", ("first", str(src)), (src,)),
        Stage(
            "second",
            ("second", str(tmp_path / "run" / "first" / "first.txt")),
            (tmp_path / "run" / "first" / "first.txt",),
        ),
    ]


def run_all(tmp_path, fake, force=False):
    run = tmp_path / "run"
    run.mkdir(exist_ok=True)
    state = load_state(run)  # with force too: it tells the run's files from the lab's
    pipeline.finish_swaps(state, run)
    for stage in stages(tmp_path):
        if not force and is_current(stage, state, run):
            pipeline.discard_unfinished(stage, run)
            continue
        check_overwrite(stage, state, run, force)
        code = run_stage(stage, run, state, fake, force)
        if code:
            return code
    return 0


def a_run_with_lab_notes_and_a_new_input(tmp_path):
    """A finished run whose first stage holds a lab's file, then an input that redoes both."""
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, FakeDoefab()) == 0
    (tmp_path / "run" / "first" / "lab_notes.txt").write_text("mine")
    (tmp_path / "input.txt").write_text("xyz")


def test_rerun_skips_unchanged_and_redoes_changed_stages(tmp_path):
    (tmp_path / "input.txt").write_text("abc")
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == ["first", "second"]
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "ABC"
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == ["first", "second"]  # nothing redone
    (tmp_path / "input.txt").write_text("xyz")
    assert run_all(tmp_path, fake) == 0
    assert fake.calls[2:] == ["first", "second"]
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "XYZ"
    assert run_all(tmp_path, fake, force=True) == 0
    assert fake.calls[4:] == ["first", "second"]


def test_interrupted_run_resumes_at_the_failed_stage(tmp_path):
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, FakeDoefab(fail_on="second")) == 2
    assert not (tmp_path / "run" / "second").exists()  # no half-written stage
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == ["second"]


def test_a_missing_input_is_refused_before_its_stage_runs(tmp_path):
    fake = FakeDoefab()
    with pytest.raises(InputError, match="input of stage 'first' is missing") as err:
        run_all(tmp_path, fake)  # no input.txt
    assert err.value.source == str(tmp_path / "input.txt")
    assert fake.calls == [] and not (tmp_path / "run" / ".first.new").exists()


def a_run_killed_while_swapping_in_its_redone_first_stage(tmp_path, monkeypatch, first_run):
    """A finished run (by ``first_run``), a new input, a rerun killed in the first swap."""
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, first_run) == 0
    (tmp_path / "input.txt").write_text("xyz")  # both stages are redone next

    def killed(path):  # a SIGKILL or power cut between the two steps of the swap
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "_remove_tree", killed)
    with pytest.raises(KeyboardInterrupt):
        run_all(tmp_path, FakeDoefab())
    monkeypatch.undo()


def test_run_killed_while_swapping_a_stage_in_resumes(tmp_path, monkeypatch):
    a_run_killed_while_swapping_in_its_redone_first_stage(tmp_path, monkeypatch, FakeDoefab())
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0  # not refused: every file there is the run's
    assert fake.calls == ["second"]  # the first stage's swap is finished, not redone
    assert (tmp_path / "run" / "first" / "first.txt").read_text() == "XYZ"
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "XYZ"


def test_a_swap_killed_and_its_new_folder_deleted_redoes_the_stage(tmp_path, monkeypatch):
    # Killed after the state named the new files, then the lab removed the hidden
    # .first.new: the old outputs left in first/ are the run's (the files they
    # replaced), not edits (refused without --force) nor the lab's (a clash).
    import shutil

    class WithAnExtra(FakeDoefab):  # the first run also writes an output the next does not
        def __call__(self, argv):
            with open(f"{argv[argv.index('--out') + 1]}/extra.txt", "w") as f:
                f.write("of the first run")
            return super().__call__(argv)

    a_run_killed_while_swapping_in_its_redone_first_stage(tmp_path, monkeypatch, WithAnExtra())
    shutil.rmtree(tmp_path / "run" / ".first.new")
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == ["first", "second"]
    assert sorted(p.name for p in (tmp_path / "run" / "first").iterdir()) == ["first.txt"]
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "XYZ"


def test_a_leftover_of_another_configuration_is_started_clean(tmp_path):
    (tmp_path / "input.txt").write_text("abc")
    leftover = tmp_path / "run" / ".first.new"
    leftover.mkdir(parents=True)
    (leftover / ".stage_key").write_text("a key of other arguments")
    (leftover / "stale.txt").write_text("from another configuration")
    assert run_all(tmp_path, FakeDoefab()) == 0
    assert sorted(p.name for p in (tmp_path / "run" / "first").iterdir()) == ["first.txt"]


def test_a_stage_key_does_not_depend_on_where_the_run_folder_lives(tmp_path):
    keys = []
    for place in ("here", "moved"):
        run = tmp_path / place / "run"
        (run / "first").mkdir(parents=True)
        (run / "first" / "first.txt").write_text("abc")
        made = run / "first" / "first.txt"
        keys.append(pipeline.stage_key(Stage("second", ("second", str(made)), (made,)), run))
    assert keys[0] == keys[1]


def test_ctrl_c_while_swapping_a_stage_in_keeps_the_labs_files(tmp_path, monkeypatch):
    # Stopped between removing the old folder and the rename, the lab's files sat in a
    # .NAME.new without a key, which the resumed run removed whole.
    import os
    import signal

    from doe.infra import interrupts

    a_run_with_lab_notes_and_a_new_input(tmp_path)
    real = pipeline._remove_tree

    def interrupted(path):
        os.kill(os.getpid(), signal.SIGINT)
        real(path)

    monkeypatch.setattr(pipeline, "_remove_tree", interrupted)
    with interrupts.handled(), pytest.raises(KeyboardInterrupt):
        run_all(tmp_path, FakeDoefab())
    monkeypatch.undo()
    assert run_all(tmp_path, FakeDoefab()) == 0
    assert (tmp_path / "run" / "first" / "lab_notes.txt").read_text() == "mine"
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "XYZ"


def test_run_killed_after_removing_the_old_folder_finishes_the_swap(tmp_path, monkeypatch):
    # A SIGKILL (no handler runs) after the old folder was removed, before the rename:
    # the lab's files then sit in the key-less .first.new, which resuming once removed.
    a_run_with_lab_notes_and_a_new_input(tmp_path)
    real = pipeline._remove_tree

    def killed_after(path):
        real(path)
        raise SystemExit("killed")

    monkeypatch.setattr(pipeline, "_remove_tree", killed_after)
    with pytest.raises(SystemExit):
        run_all(tmp_path, FakeDoefab())
    monkeypatch.undo()
    assert not (tmp_path / "run" / "first").exists()
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert (tmp_path / "run" / "first" / "lab_notes.txt").read_text() == "mine"
    assert (tmp_path / "run" / "first" / "first.txt").read_text() == "XYZ"
    assert fake.calls == ["second"]  # the first stage had finished: not redone
    assert not (tmp_path / "run" / ".first.new").exists()


def test_run_killed_before_recording_a_finished_stage_redoes_it(tmp_path, monkeypatch):
    # Killed before the state names the new files: the old folder is whole, the
    # key-less .first.new holds only the stage's outputs and is redone.
    a_run_with_lab_notes_and_a_new_input(tmp_path)

    def killed(run_dir, state):
        raise SystemExit("killed")

    monkeypatch.setattr(pipeline, "save_state", killed)
    with pytest.raises(SystemExit):
        run_all(tmp_path, FakeDoefab())
    monkeypatch.undo()
    assert (tmp_path / "run" / "first" / "first.txt").read_text() == "ABC"
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == ["first", "second"]
    assert (tmp_path / "run" / "first" / "lab_notes.txt").read_text() == "mine"
    assert (tmp_path / "run" / "second" / "second.txt").read_text() == "XYZ"


def test_edited_output_is_not_overwritten_without_force(tmp_path):
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, FakeDoefab()) == 0
    edited = tmp_path / "run" / "first" / "first.txt"
    edited.write_text("my notes")
    with pytest.raises(InputError, match="--force"):
        run_all(tmp_path, FakeDoefab())
    assert edited.read_text() == "my notes"
    assert run_all(tmp_path, FakeDoefab(), force=True) == 0
    assert edited.read_text() == "ABC"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b'{"first": {"key": "k"', "unreadable run state"),  # cut short
        (b'{"first": {"key": "\xb5"}}', "unreadable run state"),  # not UTF-8
        (b"[]", "not a run state"),
        (b'{"first": 5}', "not a run state"),
        (b'{"first": {"files": ["first.txt"]}}', "not a run state"),
        (b'{"first": {"files": {"first.txt": 7}}}', "not a run state"),
        (b'{"../first": {"files": {}}}', "not a run state"),  # its folder would be replaced
    ],
)
def test_a_run_state_that_no_run_wrote_is_refused_naming_it(tmp_path, text, message):
    # a list, a number or a non-UTF-8 byte once ended in a traceback (exit 3)
    run = tmp_path / "run"
    run.mkdir()
    (run / "run_state.json").write_bytes(text)
    with pytest.raises(InputError, match=message) as e:
        load_state(run)
    assert "run_state.json" in str(e.value) and "--force" in str(e.value)


def test_doefab_run_on_a_folder_with_a_foreign_run_state_exits_2_before_any_stage(tmp_path, capsys):
    from doe.infra.cli import main

    (tmp_path / "run_state.json").write_text("[]")
    assert main(["run", "--out", str(tmp_path)]) == 2
    assert "run_state.json: not a run state" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "run_state.json"
    ]


def test_hidden_files_links_and_empty_folders_of_the_lab_survive_a_redone_stage(tmp_path):
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, FakeDoefab()) == 0
    first = tmp_path / "run" / "first"
    (first / ".git").mkdir()
    (first / ".git" / "HEAD").write_text("ref")
    (first / ".notes").write_text("mine")
    (first / "empty").mkdir()
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "capture.tif").write_text("data")
    (first / "captures").symlink_to(tmp_path / "elsewhere")
    (tmp_path / "input.txt").write_text("xyz")  # redoes the stage
    assert run_all(tmp_path, FakeDoefab()) == 0
    assert (first / "first.txt").read_text() == "XYZ"
    assert (first / ".git" / "HEAD").read_text() == "ref"
    assert (first / ".notes").read_text() == "mine"
    assert (first / "empty").is_dir()
    assert (first / "captures").is_symlink()
    assert (first / "captures" / "capture.tif").read_text() == "data"


def test_an_unfinished_stage_folder_is_removed_once_its_stage_is_found_up_to_date(tmp_path):
    # a --force run stopped during a stage left .NAME.new with its key (for learn, its
    # checkpoint); the next run found the stage up to date, skipped it, and kept the folder
    (tmp_path / "input.txt").write_text("abc")
    assert run_all(tmp_path, FakeDoefab()) == 0
    run = tmp_path / "run"
    unfinished = run / ".first.new"
    unfinished.mkdir()
    (unfinished / ".stage_key").write_text("key of the stopped run")
    (unfinished / "checkpoint.pt").write_text("half a training")
    fake = FakeDoefab()
    assert run_all(tmp_path, fake) == 0
    assert fake.calls == [] and not unfinished.exists()
    assert (run / "first" / "first.txt").read_text() == "ABC"
