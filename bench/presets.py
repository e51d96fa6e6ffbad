"""Every embedded preset through ``doefab run``: tiling, timings and retrieval figures.

For each preset of ``doefab presets`` it prints the tiling verdict
(doe/tiling.py), then runs ``doefab run --config PRESET --steps S --formats none``
in a new process into a temporary folder and prints the seconds of each stage
(timings.json), the whole command's seconds, the tile (N, levels) and the
quantised tile's correlation, rmse and efficiency and whether it meets the
quality goals (retrieval.json). A preset whose run exits non-zero is a FAIL row,
and the script exits 1.

How it was run (the figures in bench/README.md)::

    python bench/presets.py               # --steps 200, every preset
    python bench/presets.py --steps 6000 pf32   # the preset's full training budget
    python bench/presets.py --out runs   # keeps runs/PRESET, e.g. for simulate-capture

The training budget only changes the learned PSF, not what the run must do;
200 steps keep the whole bench to a few minutes on the shared 2-core machine.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from doe.design import load_design, preset_names
from doe.records.retrieval import read_retrieval
from doe.tiling import summary_line, tiling


def run_preset(name, steps, out):
    """Run ``doefab run`` on preset ``name`` into ``out``; return (exit code, seconds, log)."""
    command = [sys.executable, "-m", "doe", "run", "--config", name, "--out", str(out)]
    command += ["--steps", str(steps), "--formats", "none"]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    return done.returncode, time.perf_counter() - start, done.stdout + done.stderr


def row(name, steps, root):
    """Return the printed row of one preset and whether its run passed."""
    code, seconds, log = run_preset(name, steps, root / name)
    if code != 0:
        return f"{name:11s} FAIL exit {code}: {log.strip().splitlines()[-1]}", False
    stages = json.loads((root / name / "timings.json").read_text())["seconds_per_stage_this_run"]
    rec = read_retrieval(root / name / "retrieve")
    q = rec.quantised
    text = (
        f"{name:11s} N={rec.tile_pixels:4d} L={rec.levels:2d}  corr {q['correlation']:.6f}  "
        f"rmse {q['rmse']:.5f}  eff {q['efficiency']:.4f}  goals {rec.goals_met}  "
        f"learn {stages['learn']:5.1f} s  retrieve {stages['retrieve']:5.1f} s  "
        f"fab {stages['fab']:5.1f} s  run {seconds:5.1f} s"
    )
    return text, True


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("presets", nargs="*", help="presets to run (default: all)")
    p.add_argument("--steps", type=int, default=200, help="training steps of each run")
    p.add_argument("--out", help="keep the run folders here, one per preset (default: discarded)")
    args = p.parse_args(argv)
    names = args.presets or preset_names()
    for name in names:
        print(f"{name:11s} tiling {summary_line(tiling(load_design(name)))}")
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        for name in names:
            text, passed = row(name, args.steps, root)
            print(text, flush=True)
            ok &= passed
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
