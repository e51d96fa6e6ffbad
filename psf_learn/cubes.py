"""Reading gated-SPAD cubes and instrument responses; writing frame images.

A cube is an (H, W, T) array of non-negative counts whose k-th sample is taken
at scan time ``k * shift``: either one ``.npy`` file or a folder of per-shift
frames (PNG/TIFF, 8 or 16 bit, single channel) sorted by file name, numbers as
numbers. The readers validate and raise InputError naming the file; they never
rescale.
"""

import re
from pathlib import Path

import numpy as np

from doe.infra.errors import InputError
from doe.infra.files import load_npy

FRAME_SUFFIXES = (".png", ".tif", ".tiff")


def check_cube(cube, source, min_samples=4, what="cube"):
    """Validate a gated cube; return it as float64 (H, W, T).

    Refuses a wrong rank, non-numeric data, NaN/inf, negative counts and
    profiles shorter than ``min_samples`` (4 to fit a return; 1 to show frames).
    """
    cube = np.asarray(cube)
    if cube.dtype.kind not in "uif":
        raise InputError(source, f"cube must hold numeric counts, got dtype {cube.dtype}")
    if cube.ndim != 3:
        raise InputError(
            source, f"cube must be (H, W, T) with T time samples, got shape {cube.shape}"
        )
    if min(cube.shape) < 1 or cube.shape[2] < min_samples:
        raise InputError(
            source,
            f"cube must have H, W >= 1 and T >= {min_samples} samples, got shape {cube.shape}",
        )
    if cube.dtype.kind == "f" and not np.all(np.isfinite(cube)):
        raise InputError(
            source,
            f"{what} contains {np.count_nonzero(~np.isfinite(cube))} NaN or infinite values",
        )
    if cube.dtype.kind in "if" and np.any(cube < 0):
        raise InputError(
            source,
            f"{what} has negative counts (min {cube.min():.6g}); counts "
            "must be >= 0 (subtract no dark level that makes them negative)",
        )
    return cube.astype(np.float64)


def read_cube(path, min_samples=4):
    """Read a gated cube from a ``.npy`` file or a folder of frames; return float64 (H, W, T).

    ``min_samples``: the fewest time samples accepted (see :func:`check_cube`).
    """
    path = Path(path)
    if path.is_dir():
        return check_cube(_read_frame_folder(path), path, min_samples)
    if not path.exists():
        raise InputError(path, "no such file or folder")
    if path.suffix.lower() != ".npy":
        raise InputError(path, "a cube must be a .npy file or a folder of PNG/TIFF frames")
    return check_cube(load_npy(path), path, min_samples)


_NUMBER = r"\d+(?:\.\d+)?"


def frame_order(path, signed=False):
    """Sort key of a frame file: its name with every number compared as a number.

    Cameras write ``frame_2`` as often as ``frame_002``; compared as text,
    ``frame_10`` would come before ``frame_2`` and scramble the scan. A decimal
    is one number: digit runs alone put ``gate_0.1ns`` (1) before ``gate_0.02ns`` (2).
    With ``signed``, a ``-`` before a number is its sign.
    """
    parts = re.split(f"({'-?' if signed else ''}{_NUMBER})", path.name)
    return [(1, float(p), p) if i % 2 else (0, 0, p) for i, p in enumerate(parts)]


def sorted_frames(paths):
    """Return the frame files in scan order (:func:`frame_order`).

    A ``-`` before a number is read as its sign only where the names differ by it
    (``t_-20ps`` beside ``t_0ps``, which unsigned would sort after 0 and scramble the
    scan), not where
    every name has it (``frame-10`` is frame 10).
    """
    signed = _minus_is_sign(paths)
    return sorted(paths, key=lambda p: frame_order(p, signed))


def _minus_is_sign(paths):
    def shapes(signed):
        return {re.sub(f"{'-?' if signed else ''}{_NUMBER}", "#", p.name) for p in paths}

    return len(shapes(signed=False)) > 1 and len(shapes(signed=True)) == 1


def _frame_files(folder):
    """The frame files of a folder, in scan order; hidden files aside (macOS's
    "._frame_001.png" metadata)."""
    return sorted_frames(
        [
            p
            for p in Path(folder).iterdir()
            if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES and not p.name.startswith(".")
        ]
    )


def scan_gaps(path):
    """Return notes on frames missing from a folder's scan (none for an .npy cube).

    Every frame is taken as one scan step, so a lost frame moves every later
    return by a step. Where one number alone varies across the names, and its
    steps are whole multiples of the smallest with some larger, a frame is missing.
    """
    path = Path(path)
    if not path.is_dir():
        return []
    files = _frame_files(path)
    signed = _minus_is_sign(files)
    keys = [[k[1] for k in frame_order(p, signed) if k[0]] for p in files]
    if len(files) < 3 or len({len(k) for k in keys}) != 1:
        return []
    numbers = np.array(keys, dtype=np.float64)
    varying = np.flatnonzero(np.ptp(numbers, axis=0) > 0)
    if varying.size != 1:
        return []
    steps = np.diff(numbers[:, varying[0]])
    if not steps.min() > 0:
        return []
    ratio = steps / steps.min()
    if not (np.allclose(ratio, np.round(ratio), rtol=0, atol=1e-6) and ratio.max() > 1.5):
        return []
    k = int(np.argmax(ratio > 1.5))  # the first gap
    missing = int(np.round(ratio).sum()) - steps.size
    return [
        f"the frame names step by {steps.min():g} but jump from {files[k].name} to "
        f"{files[k + 1].name} ({missing} frame(s) missing in all?); every frame is taken as "
        "one --shift-ps step, so returns after a gap come out late"
    ]


def _read_frame_folder(folder):
    files = _frame_files(folder)
    if not files:
        raise InputError(folder, f"no frames ({', '.join(FRAME_SUFFIXES)}) in this folder")
    frames = [read_frame(p) for p in files]
    shape, dtype = frames[0].shape, frames[0].dtype
    for p, f in zip(files, frames, strict=True):
        if f.shape != shape:
            raise InputError(
                p,
                f"frame is {f.shape[0]} x {f.shape[1]} (rows x columns), the first frame "
                f"{files[0].name} is {shape[0]} x {shape[1]}",
            )
        if f.dtype != dtype:  # e.g. float frames in [0, 1] among 16-bit counts
            raise InputError(
                p, f"frame is stored as {f.dtype}, the first frame {files[0].name} as {dtype}"
            )
        check_cube(f[..., None], p, min_samples=1, what="frame")  # name the frame at fault
    return np.stack(frames, axis=-1)


def read_frame(path):
    """Read one single-channel frame keeping its integer type (uint8/uint16) or float32."""
    import OpenImageIO as oiio

    from doe.infra.image_pages import (
        check_file_kind,
        has_more_pages,
        native_stderr_quiet,
        stored_bits,
        stored_codes,
    )

    path = Path(path)
    check_file_kind(path)
    with native_stderr_quiet():  # libpng's own "libpng error: ..." line; geterror() has it
        inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"not a readable image ({oiio.geterror()})")
    try:
        spec = inp.spec()
        if spec.nchannels != 1:
            raise InputError(path, f"frame must be single-channel, has {spec.nchannels} channels")
        base = spec.format.basetype
        if base == oiio.UINT8:
            fmt = "uint8"
        elif base == oiio.UINT16:
            fmt = "uint16"
        elif base in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE):
            fmt = "float"
        else:
            raise InputError(path, f"unsupported pixel type {spec.format}; use 8/16-bit or float")
        with native_stderr_quiet():
            pixels = inp.read_image(0, 0, 0, 1, fmt)
        if pixels is None:
            raise InputError(path, f"could not read the pixels ({inp.geterror()})")
        if has_more_pages(inp):  # a multi-page TIFF: which page is this shift's frame?
            raise InputError(path, "holds several images (pages); give one frame per file")
        # Counts as stored: a 12-bit TIFF's 4095 comes as 65535, a 1-bit PNG's 1 as 255.
        bits = stored_bits(spec, path)
    finally:
        inp.close()
    return stored_codes(np.asarray(pixels).reshape(spec.height, spec.width), bits)


def read_irf(path):
    """Read a measured instrument response: a 1-D ``.npy`` array of >= 4 finite samples."""
    irf = load_npy(path)
    if irf.dtype.kind not in "uif":
        raise InputError(path, f"IRF must be numeric, got dtype {irf.dtype}")
    irf = np.squeeze(irf)
    if irf.ndim != 1 or irf.size < 4:
        raise InputError(path, f"IRF must be 1-D with at least 4 samples, got shape {irf.shape}")
    irf = irf.astype(np.float64)
    if not np.all(np.isfinite(irf)):
        raise InputError(path, "IRF contains NaN or infinite values")
    if not irf.max() > 0:
        raise InputError(path, "IRF has no positive sample")
    return irf


def write_frame_png16(path, frame):
    """Write a (H, W) array in [0, 1] as a 16-bit single-channel PNG."""
    import OpenImageIO as oiio

    data = np.round(np.clip(frame, 0.0, 1.0) * 65535).astype(np.uint16)
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], 1, oiio.UINT16)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    if not out.open(str(path), spec):  # the reason is the writer's, not in oiio.geterror()
        raise OSError(f"cannot write {path}: {out.geterror()}")
    try:
        # OpenImageIO scrambles a 2-D array; (H, W, 1) is read as intended.
        if not out.write_image(data[:, :, None]):
            raise OSError(f"cannot write {path}: {out.geterror()}")
    finally:
        out.close()


def super_resolve_cube(model_dir, cube):
    """Super-resolve every time bin of an (H, W, T) cube; return (fH, fW, T) counts >= 0.

    All bins share one white level, the cube's maximum, which keeps the frames on
    a common scale. torch is imported here, by :mod:`psf_learn.sr`, and only here.
    """
    from psf_learn.sr import super_resolve

    if not Path(model_dir).is_dir():
        raise InputError(model_dir, "no such model folder (write one with 'doefab learn')")
    frames = np.moveaxis(cube, -1, 0)
    white = float(frames.max()) or 1.0
    hr = np.asarray(super_resolve(model_dir, frames, photons=white), dtype=np.float64)
    if hr.ndim != 3 or hr.shape[0] != frames.shape[0]:
        raise InputError(
            model_dir, f"super-resolution returned shape {hr.shape} for frames {frames.shape}"
        )
    # The network is not photon-exact: negative undershoot is not a count.
    return np.clip(np.moveaxis(hr, 0, -1), 0.0, None)
