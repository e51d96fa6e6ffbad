"""Benchmark ``doefab fab`` on a dense random 8-level N=175 design (the default preset).

Prints the wall time of the whole command (subprocess, median of --repeat runs)
and the GDS size, beside a flat write of the same layout (every tile's
polygons copied into the top cell, no AREF): build + write time and file size.
The flat file (~330 MB, ~1.3 GB of memory while building) is written to a
temporary folder and deleted.

Run: ``python bench/package.py [--repeat 3] [--no-flat]``
"""

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from doe.infra import flags


def make_design(path, n=175, n_levels=8, k=11, seed=0):
    from doe.fraunhofer import simulate_levels

    path.mkdir(parents=True)
    levels = np.random.default_rng(seed).integers(0, n_levels, (n, n)).astype(np.uint8)
    np.save(path / "levels.npy", levels)
    np.save(path / "target_psf.npy", simulate_levels(levels, n_levels, k)[0])
    return levels


def time_cli(design, out, repeat):
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        cmd = [
            sys.executable,
            "-m",
            "doe",
            "fab",
            str(design),
            "--out",
            str(out / f"r{i}"),
        ]
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return times


def time_library(levels, flat, repeat, path):
    from doe.derived import derive
    from doe.design import load_design
    from fab.package.masks import masks_from_levels
    from layouts.gds import build_library, write_gds

    der = derive(load_design())
    masks = masks_from_levels(levels, 8, der.level_step)
    pitch_nm = round(der.mask_pixel_pitch * 1e9)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        lib, info = build_library(masks, pitch_nm, (der.tiles, der.tiles), "bench", flat=flat)
        write_gds(lib, path)
        times.append(time.perf_counter() - t0)
        del lib
    size = path.stat().st_size
    path.unlink()
    return times, size, sum(info.polygon_counts.values())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=flags.count, default=3)
    ap.add_argument("--no-flat", action="store_true", help="skip the flat write")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        levels = make_design(tmp / "design")
        cli = time_cli(tmp / "design", tmp / "out", args.repeat)
        gds_size = (tmp / "out" / "r0" / "mask.gds").stat().st_size
        hier, hier_size, n_rect = time_library(levels, False, args.repeat, tmp / "h.gds")
        print(f"dense random 8-level design, N=175, 16 x 16 tiles; {n_rect} rectangles per tile")
        print(f"{'':34s}{'median s':>10s}{'runs':>6s}{'size MiB':>10s}")
        print(
            f"{'doefab fab (whole command)':34s}{statistics.median(cli):10.2f}"
            f"{len(cli):6d}{gds_size / 2**20:10.2f}"
        )
        print(
            f"{'GDS build+write, AREF':34s}{statistics.median(hier):10.2f}"
            f"{len(hier):6d}{hier_size / 2**20:10.2f}"
        )
        if not args.no_flat:
            flat, flat_size, _ = time_library(levels, True, 1, tmp / "f.gds")
            print(
                f"{'GDS build+write, flat (no AREF)':34s}{statistics.median(flat):10.2f}"
                f"{len(flat):6d}{flat_size / 2**20:10.2f}"
            )
            print(
                f"flat / AREF: time x{statistics.median(flat) / statistics.median(hier):.0f}, "
                f"size x{flat_size / hier_size:.0f}"
            )
        print(
            f"budget: doefab fab <= 30 s, GDS <= 5 MB -> "
            f"{'OK' if statistics.median(cli) <= 30 and gds_size <= 5e6 else 'OVER'}"
        )


if __name__ == "__main__":
    main()
