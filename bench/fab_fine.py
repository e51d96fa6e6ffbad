"""Benchmark ``doefab fab`` and ``doefab mesh`` on the largest tile doefab accepts.

A random 8-level N x N map is the worst case for the rectangle count and the
mesh; N = 4096 is the largest tile a design may have (``MAX_TILE_PIXELS``; about
a 0.213 um pitch at f = 50 mm, the default preset otherwise; 0.25 um gives
N = 3493). Prints the wall time and the peak resident memory of each command (a
subprocess, its rusage as the parent reaps it: a command killed by the kernel
still reports its peak), and what each says (``mesh`` refuses a tile whose mesh
would exceed 8 GiB).

Run: ``python bench/fab_fine.py [--n 4096]`` (about 8 minutes and 4.5 GB at 4096)
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from doe.design import MAX_TILE_PIXELS


def run(argv):
    """Run a doefab command; return (exit code, seconds, peak RSS in GB, its last message)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, "-m", "doe", *argv], stdout=out, stderr=err)
        _, status, usage = os.wait4(p.pid, 0)  # Linux: ru_maxrss in KiB
        seconds = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        said = (err.read() if p.returncode else out.read()).strip().splitlines() or [""]
    return p.returncode, seconds, usage.ru_maxrss * 1024 / 1e9, said[-1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--n", type=int, default=MAX_TILE_PIXELS, help=f"tile pixels N (default {MAX_TILE_PIXELS})"
    )
    args = ap.parse_args()
    if not 1 <= args.n <= MAX_TILE_PIXELS:
        ap.error(f"--n must lie between 1 and {MAX_TILE_PIXELS}, got {args.n}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        design = tmp / "design"
        design.mkdir()
        levels = np.random.default_rng(0).integers(0, 8, (args.n, args.n)).astype(np.uint8)
        np.save(design / "levels.npy", levels)
        print(f"random 8-level map, N = {args.n}")
        print(f"{'command':8s} {'exit':>4s} {'seconds':>8s} {'peak GB':>8s}")
        for name, argv in (
            ("fab", ["fab", str(design), "--out", str(tmp / "fab")]),
            ("mesh", ["mesh", str(tmp / "fab"), "--out", str(tmp / "mesh"), "--formats", "ply"]),
        ):
            code, seconds, peak, last = run(argv)
            print(f"{name:8s} {code:4d} {seconds:8.1f} {peak:8.2f}   {last[:150]}")


if __name__ == "__main__":
    main()
