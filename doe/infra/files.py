"""Reading and writing the contract files (psf.npy, levels.npy, JSON) safely.

Readers validate against CONVENTIONS.md and raise InputError naming the file;
writers go through a staging folder so that a failed or killed command leaves
no half-written output behind.
"""

import contextlib
import glob
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

import numpy as np

from doe.infra import interrupts
from doe.infra.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


def load_npy(path):
    """Load a .npy array without pickles, raising InputError if unreadable."""
    path = Path(path)
    if path.is_dir():  # e.g. a stage's output folder given for the file in it
        inside = sorted(p.name for p in path.glob("*.npy"))
        held = ", ".join(inside[:4]) + (" ..." if len(inside) > 4 else "") or "no .npy file"
        raise InputError(path, f"is a folder, not a .npy file (it holds {held})")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":  # np.load would open an .npz or suggest allow_pickle
            if magic.startswith(b"PK"):
                raise InputError(path, "is an .npz archive (numpy.savez), not a .npy array")
            raise InputError(path, "is not a .npy file (it lacks the header numpy.save writes)")
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (OSError, ValueError, EOFError) as e:
        raise InputError(path, f"not a readable .npy array ({e})") from None
    except MemoryError:  # a damaged header can claim terabytes
        raise InputError(path, "its header claims an array too large for memory") from None


def check_psf(psf, source, tol=1e-6):
    """Validate a PSF array against the contract; return it as float64 normalised to sum 1.

    A sum within ``tol`` of 1 is renormalised exactly; any other non-zero sum is
    refused, so a PSF is never silently rescaled.
    """
    psf = np.asarray(psf)
    if psf.dtype.kind != "f":
        raise InputError(source, f"PSF must be a float array, got dtype {psf.dtype}")
    if psf.dtype.itemsize < 4:  # 3 significant digits: no sum within tol of 1
        raise InputError(source, f"PSF must be float64 (or float32), got {psf.dtype}")
    if psf.ndim != 2 or psf.shape[0] != psf.shape[1]:
        raise InputError(source, f"PSF must be square (K, K), got shape {psf.shape}")
    if psf.shape[0] % 2 == 0:
        raise InputError(
            source, f"PSF size K must be odd (centre = optical axis), got {psf.shape[0]}"
        )
    if not np.all(np.isfinite(psf)):
        raise InputError(source, "PSF contains NaN or infinite values")
    if np.any(psf < 0):
        raise InputError(source, f"PSF has negative values (min {psf.min():.3g})")
    # Summed in float64 and C order: a float32 sum rounds, and a Fortran-ordered copy
    # summed to another last bit (so another design for the same values and seed).
    psf = np.ascontiguousarray(psf, dtype=np.float64)
    total = float(psf.sum())
    if total <= 0:
        raise InputError(source, "PSF sums to zero")
    if abs(total - 1) > tol:
        raise InputError(source, f"PSF must sum to 1 (sums to {total:.10g}); normalise it first")
    return psf / total


def read_psf(path):
    """Read and validate ``psf.npy``; return float64 (K, K) summing to 1."""
    return check_psf(load_npy(path), path)


# levels.npy is uint8 (CONVENTIONS.md), so a design has at most 256 levels (8 masks).
MAX_LEVELS = 256
LEVEL_COUNT_RULE = "a power of two from 2 to 256 (one binary mask per bit; levels.npy is uint8)"


def is_level_count(n_levels):
    """True for a phase-level count L that masks and ``levels.npy`` can hold."""
    return 2 <= n_levels <= MAX_LEVELS and n_levels & (n_levels - 1) == 0


def check_levels(levels, n_levels, source):
    """Validate a level map against the contract; return it as uint8 (N, N)."""
    levels = np.asarray(levels)
    if levels.dtype != np.uint8:
        raise InputError(source, f"levels must be uint8, got dtype {levels.dtype}")
    if levels.ndim != 2 or levels.shape[0] != levels.shape[1]:
        raise InputError(source, f"levels must be square (N, N), got shape {levels.shape}")
    if levels.size and levels.max() >= n_levels:
        raise InputError(source, f"levels must lie in 0..{n_levels - 1}, found {levels.max()}")
    return levels


def read_levels(path, n_levels):
    """Read and validate ``levels.npy`` for ``n_levels`` phase levels."""
    return check_levels(load_npy(path), n_levels, path)


def read_json(path):
    """Read a JSON object (every doefab JSON file is one) as a dict.

    Raises InputError naming the file if it is missing, malformed or not an object.
    """
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"not readable JSON ({e})") from None
    if not isinstance(obj, dict):
        raise InputError(path, f"expected a JSON object, got {type(obj).__name__}")
    return obj


def previous_files(record, names_of):
    """Return the files an earlier run listed in its JSON ``record``, read by ``names_of(obj)``.

    For :func:`staged_output`'s ``stale``; empty when there is no such record or
    it cannot be read (then nothing is removed).
    """
    try:
        names = names_of(json.loads(Path(record).read_text()))
        return [] if isinstance(names, str) else [str(name) for name in names]
    except (OSError, ValueError, LookupError, TypeError, AttributeError):
        return []


def write_json(path, obj):
    """Write ``obj`` as indented, key-sorted JSON (deterministic bytes), atomically.

    Numpy scalars and arrays become numbers and lists. JSON has no NaN or
    infinity (strict readers refuse Python's ``NaN``), so a figure that is
    undefined -- the correlation with a uniform target -- is written as null.
    """
    text = json.dumps(_plain(obj), indent=2, sort_keys=True, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode())


def _plain(o):
    """Return ``o`` with numpy values as Python ones and non-finite floats as None."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return None
    if isinstance(o, Path):
        return str(o)
    return o


def save_npy(path, array):
    """Save an array as .npy atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        np.save(f, np.asarray(array), allow_pickle=False)
    os.replace(tmp, path)


def atomic_write_bytes(path, data):
    """Write bytes to ``path`` via a temporary file and rename (old or new, never half)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual file mode
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def staged_output(out_dir, force=False, names=None, stale=()):
    """Yield a temporary folder; on success move its files into ``out_dir``.

    Nothing appears in ``out_dir`` unless the block finishes, so a failed
    command leaves no half-written output. Existing files in ``out_dir`` that the
    command would write are refused unless ``force``.

    Parameters
    ----------
    out_dir : path
        Final output folder (created if needed).
    force : bool
        Overwrite files that already exist in ``out_dir``.
    names : iterable of str or None
        Files the command will write, checked up front; when None the check
        happens at the end against what was actually written.
    stale : iterable of str
        Files an earlier run of the command wrote in ``out_dir`` (read from its
        manifest). With ``force`` those it did not write again are removed, so
        that no file of the old package contradicts the new one (an old
        ``mask.oas`` beside a new ``mask.gds``).
    """
    out_dir = Path(out_dir)
    check_out_folder(out_dir)
    if names is not None and not force:
        _refuse_overwrite(out_dir, names)
    try:
        stage = _staging_folder(out_dir)
    except OSError as e:
        raise InputError(out_dir, f"cannot write here ({e.strerror})") from None
    try:
        yield stage
        written = sorted(p.relative_to(stage) for p in stage.rglob("*") if p.is_file())
        if not force:
            _refuse_overwrite(out_dir, [str(p) for p in written])
        interrupts.check()  # asked to stop while a library held the signal: publish nothing
        out_dir.mkdir(parents=True, exist_ok=True)
        with interrupts.deferred():  # stopped half-way, the package would be half old
            for rel in written:
                dest = out_dir / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.replace(stage / rel, dest)
                except OSError as e:  # name the output, not the staging file that vanishes
                    raise OSError(e.errno, e.strerror, str(dest)) from None
            if force:
                for rel in sorted(set(map(Path, stale)) - set(written)):
                    inside = not rel.is_absolute() and ".." not in rel.parts
                    if inside and (out_dir / rel).is_file():
                        (out_dir / rel).unlink()
                        with contextlib.suppress(OSError):  # a sub-folder it emptied
                            if rel.parent != Path():
                                (out_dir / rel.parent).rmdir()
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _staging_folder(out_dir):
    """Make the staging folder on out_dir's file system: files are moved, not copied, in.

    Beside out_dir as a rule; inside it when it is a mount point or a link to
    another file system (a container's bind mount), where a move from beside it
    fails ("Invalid cross-device link").
    """
    parent = out_dir.parent
    parent.mkdir(parents=True, exist_ok=True)
    if out_dir.is_dir() and os.stat(out_dir).st_dev != os.stat(parent).st_dev:
        where, prefix = out_dir, ".staging-"
    else:
        where, prefix = parent, f".{out_dir.name}.staging-"
    # host and process in the name: a run killed outright (SIGKILL, power cut) leaves its
    # folder behind; the next run into out_dir removes those of processes now gone
    prefix += f"{re.sub(r'[^A-Za-z0-9]', '_', socket.gethostname())}-"
    _remove_orphans(where, prefix)
    return Path(tempfile.mkdtemp(dir=where, prefix=f"{prefix}{os.getpid()}-"))


def _remove_orphans(where, prefix):
    """Remove the staging folders ``where/prefix<pid>-*`` of processes of this host that
    are gone (another host's cannot be told alive from here, and stay)."""
    for folder in where.glob(f"{glob.escape(prefix)}*"):
        pid = re.match(r"(\d+)-", folder.name[len(prefix) :])
        if pid and folder.is_dir() and not _alive(int(pid[1])):
            shutil.rmtree(folder, ignore_errors=True)


def _alive(pid):
    try:
        os.kill(pid, 0)  # signal 0: is there such a process
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's, or no such pid number
        return True
    return True


def sha256_file(path):
    """Return the hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_out_folder(out_dir):
    """Refuse an output folder path that is taken by a file."""
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise InputError(out_dir, "output path exists and is not a folder")


def _refuse_overwrite(out_dir, names):
    clash = [n for n in names if (Path(out_dir) / n).exists()]
    if clash:
        raise InputError(
            out_dir,
            f"would overwrite {', '.join(sorted(clash)[:4])}"
            f"{' ...' if len(clash) > 4 else ''}; use --force or another --out",
        )
