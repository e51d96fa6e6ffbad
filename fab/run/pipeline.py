"""The whole pipeline as a list of stages with content-hash skipping and resume.

Each stage is one ``doefab`` subcommand writing into its own folder of the run
directory. A stage's key is the SHA-256 of its arguments, the contents of its
input files and the values of the resolved design it reads; ``run_state.json``
records, per finished stage, the key and the SHA-256 of every file it wrote and
of the files those replaced. A re-run skips a stage whose key and files are unchanged (so an
interrupted run resumes at the first unfinished stage), redoes it when an input
changed, and never overwrites a file that was edited since the run wrote it
unless ``force``. A lab's own files in a stage's folder (names the run never
wrote) are kept through every re-run, ``force`` included.
"""

import contextlib
import hashlib
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from doe.infra.errors import InputError
from doe.infra.files import sha256_file

STATE_FILE = "run_state.json"
LOCK_FILE = ".doefab_run.lock"  # hidden: not a product; kept, so every run locks one inode


@dataclass(frozen=True)
class Stage:
    """One step of the pipeline.

    ``argv`` is the doefab command line without ``--out``/``--force``; paths in it
    that are inside the run folder are written relative to it so that the key
    does not depend on where the run folder lives. ``config`` (``--config FILE``)
    runs with the stage but does not key it: ``design``, the resolved design's values
    that the stage reads as canonical JSON, does, so that a comment in the design
    file, or the file moved, redoes nothing while any changed value it reads redoes
    the stage.
    """

    name: str
    argv: tuple[str, ...]
    inputs: tuple[Path, ...] = field(default=())
    config: tuple[str, ...] = field(default=())
    design: str = ""

    @property
    def command(self):
        """The doefab command line it runs, without ``--out``/``--force``."""
        return (*self.argv, *self.config)


@contextlib.contextmanager
def run_lock(run_dir):
    """Hold the run folder for one ``doefab run``; refuse a second one (InputError).

    Two runs in one folder share its staging folders and state file, and would
    leave a mix of both. The lock is the kernel's (flock): closing the file, or
    the end of the process, releases it.
    """
    path = Path(run_dir) / LOCK_FILE
    with open(path, "a+") as f:
        try:
            import fcntl

            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "unknown"
            raise InputError(
                run_dir, f"another doefab run (pid {holder}) is writing this folder; "
                "wait for it to finish or use another --out",
            ) from None  # fmt: skip
        except (ImportError, OSError) as e:  # no POSIX locks, or a file system without them
            print(
                f"doefab run: warning: cannot lock {path} ({e}); nothing stops a second "
                "run in this folder",
                file=sys.stderr,
            )
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        yield


def stage_key(stage, run_dir):
    """Return the content key of a stage: its arguments, its inputs' bytes, its design."""
    run_dir = Path(run_dir).resolve()
    argv = [_relative(a, run_dir) for a in stage.argv]
    inputs = {}
    for p in stage.inputs:
        if not Path(p).is_file():
            raise InputError(p, f"input of stage {stage.name!r} is missing")
        inputs[_relative(str(p), run_dir)] = sha256_file(p)
    blob = {"argv": argv, "inputs": inputs, "design": stage.design}
    blob = json.dumps(blob, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()


def _relative(arg, run_dir):
    p = Path(arg)
    try:
        return str(p.resolve().relative_to(run_dir)) if p.exists() or p.is_absolute() else arg
    except ValueError:
        return arg


def stage_files(folder):
    """Return {relative path: sha256} of every file below ``folder`` (hidden files skipped)."""
    folder = Path(folder)
    return {
        str(p.relative_to(folder)): sha256_file(p)
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)
    }


def load_state(run_dir):
    """Return ``run_state.json``: {stage: {"key", "files", "replaces", "seconds"}}, or {}.

    Raises InputError for a file that is no such record (edited, or another
    tool's), such as a stage named "../x": finish_swaps joins the names to the run
    folder, and that one points outside it.
    """
    path = Path(run_dir) / STATE_FILE
    if not path.exists():
        return {}
    try:
        state = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"unreadable run state ({e}); use --force to start over") from None
    if not _is_state(state):
        raise InputError(path, "not a run state written by doefab run; use --force to start over")
    return state


def _is_state(state):
    def is_file_map(files):
        return isinstance(files, dict) and all(isinstance(h, str) for h in files.values())

    return isinstance(state, dict) and all(
        Path(name).name == name
        and name not in ("", ".", "..")
        and isinstance(rec, dict)
        and is_file_map(rec.get("files", {}))
        and is_file_map(rec.get("replaces", {}))
        for name, rec in state.items()
    )


def is_current(stage, state, run_dir):
    """True when ``stage`` finished before with the same key and its outputs untouched.

    Files of the lab's own beside them do not count.
    """
    rec = state.get(stage.name)
    if not rec or rec.get("key") != stage_key(stage, run_dir):
        return False
    files = stage_files(Path(run_dir) / stage.name)
    return all(files.get(p) == h for p, h in rec.get("files", {}).items())


def edited_files(stage, state, run_dir):
    """Return the files of a stage's folder that the run wrote and that were edited since.

    A file is the run's when the stage's record names it (its files, or the ones
    those replaced: a run killed while swapping a stage in leaves either).
    """
    folder = Path(run_dir) / stage.name
    if not folder.exists():
        return []
    rec = state.get(stage.name, {})
    ours = [rec.get("files", {}), rec.get("replaces", {})]
    return [
        p
        for p, h in stage_files(folder).items()
        if any(p in f for f in ours) and all(f.get(p) != h for f in ours)
    ]


def check_overwrite(stage, state, run_dir, force):
    """Refuse to redo a stage whose folder holds outputs edited since the run wrote them."""
    edited = [] if force else edited_files(stage, state, run_dir)
    if edited:
        raise InputError(
            Path(run_dir) / stage.name / edited[0],
            f"edited since this run wrote it ({len(edited)} such file(s)); "
            "use --force to overwrite or choose another --out",
        )


def own_files(stage, state, run_dir):
    """Return the files of a stage's folder that the run never wrote (the lab's own)."""
    return _own_files(state.get(stage.name, {}), Path(run_dir) / stage.name)


def _own_files(rec, folder):
    """Every entry of ``folder`` the run did not write: hidden files, links and empty
    folders included (stage_files skips them, and the swap would remove them with the
    folder)."""
    ours = {*rec.get("files", {}), *rec.get("replaces", {})}
    folder = Path(folder)
    own = []
    for root, dirs, files in os.walk(folder):  # a linked folder is one entry, not followed
        here = Path(root)
        for d in [d for d in dirs if (here / d).is_symlink()]:
            dirs.remove(d)
            own.append(str((here / d).relative_to(folder)))
        own += [str((here / f).relative_to(folder)) for f in files]
        if here != folder and not dirs and not files:
            own.append(str(here.relative_to(folder)))  # an empty folder of the lab's
    return sorted(p for p in own if p not in ours)


def discard_unfinished(stage, run_dir):
    """Remove the ``.NAME.new`` of a stage found up to date that an interrupted run left
    unfinished (it still holds its key): no later run would, and a --force run stopped
    during training would leave its checkpoint there for good."""
    new = Path(run_dir) / f".{stage.name}.new"
    if (new / ".stage_key").exists():
        _remove_tree(new)


def run_stage(stage, run_dir, state, invoke, force=False):
    """Run one stage into a fresh folder and swap it in; record it in the state.

    ``invoke(argv) -> exit code`` runs a doefab command. The stage writes to
    ``.NAME.new`` (kept across an interrupt, so a stage with its own checkpoints,
    such as training, resumes there), which replaces ``NAME`` only on success.
    The lab's own files in ``NAME`` move into the new folder; one that the stage
    now writes under the same name is refused (InputError) unless ``force``.
    """
    run_dir = Path(run_dir)
    key = stage_key(stage, run_dir)
    new = run_dir / f".{stage.name}.new"
    # Staging folders of a stage killed before it could clean up (the run holds the lock).
    for leftover in run_dir.glob(f".{new.name}.staging-*"):
        _remove_tree(leftover)
    key_file = new / ".stage_key"
    if new.exists() and (not key_file.exists() or key_file.read_text() != key):
        _remove_tree(new)  # a leftover of another configuration: start clean
    new.mkdir(parents=True, exist_ok=True)
    key_file.write_text(key)
    code = invoke([*stage.command, "--out", str(new), "--force"])
    if code != 0:
        return code
    key_file.unlink()  # it marks an unfinished stage; the package holds only the stage's files
    seconds = move_timings(new)
    # Record the new files before swapping them in, keeping the record of the
    # files they replace: a run killed during the swap then finds only files it
    # can account for, and resumes instead of refusing them as foreign.
    replaced = state.get(stage.name, {}).get("files", {})
    final = run_dir / stage.name
    keep = own_files(stage, state, run_dir) if final.exists() else []
    clash = [rel for rel in keep if (new / rel).exists()]
    if clash and not force:
        raise InputError(
            final / clash[0],
            "not written by this run, and the stage now writes a file of that name; "
            "move it, or use --force to overwrite it",
        )
    from doe.infra import interrupts

    state[stage.name] = {
        "key": key,
        "files": stage_files(new),
        "replaces": replaced,
        "seconds": seconds,
    }
    # Not stopped half-way by Ctrl-C (a SIGKILL is mended by finish_swaps on resume).
    with interrupts.deferred():
        save_state(run_dir, state)
        _swap_in(new, final, keep)
    return 0


def _swap_in(new, final, keep):
    """Move the lab's files ``keep`` from ``final`` into ``new``, then replace ``final``."""
    for rel in keep:  # unless the stage wrote a file of that name
        if ((final / rel).exists() or (final / rel).is_symlink()) and not (new / rel).exists():
            (new / rel).parent.mkdir(parents=True, exist_ok=True)
            (final / rel).rename(new / rel)
    if final.exists():
        _remove_tree(final)
    new.rename(final)


def finish_swaps(state, run_dir):
    """Finish the swaps of stages that a killed run (SIGKILL, power cut) left half done.

    A ``.NAME.new`` without its key is a finished stage. Once the state records its
    files, the swap may have moved the lab's files into it and removed ``NAME``:
    removing it as a leftover would lose them, so the swap is completed instead.
    Before that record, ``NAME`` is untouched and run_stage redoes the stage.
    """
    run_dir = Path(run_dir)
    for name, rec in state.items():
        new, final = run_dir / f".{name}.new", run_dir / name
        if not isinstance(rec, dict) or not new.is_dir() or (new / ".stage_key").exists():
            continue
        files = stage_files(new)
        if rec.get("files") and all(files.get(p) == h for p, h in rec["files"].items()):
            _swap_in(new, final, _own_files(rec, final) if final.exists() else [])


def move_timings(folder):
    """Take the wall-clock ``seconds`` out of a stage's JSON reports; return them.

    Timings differ from run to run; recorded apart (the run's ``timings.json``)
    they leave every product byte-identical for the same inputs and seed. The
    reports keep the key, set to null.
    """
    from doe.infra.files import write_json

    seconds = {}
    for path in sorted(Path(folder).glob("*.json")):
        try:
            report = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(report, dict) and report.get("seconds") is not None:
            seconds[path.name] = report["seconds"]
            write_json(path, {**report, "seconds": None})
    return seconds


def save_state(run_dir, state):
    from doe.infra.files import write_json

    write_json(Path(run_dir) / STATE_FILE, state)


def _remove_tree(path):
    import shutil

    shutil.rmtree(path)
