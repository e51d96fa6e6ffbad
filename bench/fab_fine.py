"""Benchmark ``doefab fab`` and ``doefab mesh`` at the finest mask pitch.

A random 8-level N x N map is the worst case for the rectangle count and the
mesh; N = 3494 is the tile of a 0.25 um pitch design (f = 50 mm, the default
preset otherwise), the largest below the 4096-pixel limit. Prints the wall time
and the peak resident memory of each command (a subprocess; Linux ru_maxrss), and
what each says (``mesh`` refuses a tile whose mesh would exceed 8 GiB).

Run: ``python bench/fab_fine.py [--n 3494]`` (about 6 minutes and 3 GB at 3494)
"""

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# Runs one command and reports its own peak resident memory (Linux: ru_maxrss in KiB).
_CHILD = (
    "import resource, sys\n"
    "from doe.cli import main\n"
    "code = main(sys.argv[1:])\n"
    "print('MAXRSS_KIB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
    "sys.exit(code)\n"
)


def run(argv):
    """Run a doefab command; return (exit code, seconds, peak RSS in GB, its last message)."""
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-c", _CHILD, *argv], capture_output=True, text=True, check=False
    )
    seconds = time.perf_counter() - t0
    err = p.stderr.strip().splitlines()
    peak_gb = int(err.pop().split()[1]) * 1024 / 1e9 if err and "MAXRSS_KIB" in err[-1] else 0.0
    said = (err if p.returncode else p.stdout.strip().splitlines()) or [""]
    return p.returncode, seconds, peak_gb, said[-1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=3494, help="tile pixels N (default 3494)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        design = tmp / "design"
        design.mkdir()
        levels = np.random.default_rng(0).integers(0, 8, (args.n, args.n)).astype(np.uint8)
        np.save(design / "levels.npy", levels)
        print(f"random 8-level map, N = {args.n} (the default design's tile, at its pitch)")
        print(f"{'command':8s} {'exit':>4s} {'seconds':>8s} {'peak GB':>8s}")
        for name, argv in (
            ("fab", ["fab", str(design), "--out", str(tmp / "fab")]),
            ("mesh", ["mesh", str(tmp / "fab"), "--out", str(tmp / "mesh"), "--formats", "ply"]),
        ):
            code, seconds, peak, last = run(argv)
            print(f"{name:8s} {code:4d} {seconds:8.1f} {peak:8.2f}   {last[:150]}")


if __name__ == "__main__":
    main()
