"""Train several ``doefab learn`` models side by side: the runner of table2.py and learn_levers.py.

Each model is its own process (one log file per model in the work folder), so a
step budget gives the same model whatever else runs beside it.
"""

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def train_all(out, jobs, parallel=1, common=()):
    """Run ``doefab learn --out OUT/KEY FLAGS COMMON`` for each (key, flags), ``parallel`` at once.

    Every process gets cores / ``parallel`` threads; a failed training ends the script
    naming its log.
    """
    threads = str(max(1, (os.cpu_count() or 1) // parallel))
    queue, running = list(jobs), []
    while queue or running:
        while queue and len(running) < parallel:
            key, flags = queue.pop(0)
            cmd = [sys.executable, "-m", "doe", "learn", "--out", str(Path(out) / key)]
            cmd += [*flags, "--threads", threads, *common]
            log = open(Path(out) / f"{key}.log", "w")  # closed when the process ends
            print(f"training {key}: {' '.join(cmd[2:])}", file=sys.stderr)
            running.append((key, subprocess.Popen(cmd, stdout=log, stderr=log, cwd=ROOT), log))
        time.sleep(2)
        for item in list(running):
            key, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode:
                    sys.exit(f"training {key} failed, see {Path(out) / (key + '.log')}")
                print(f"trained {key}", file=sys.stderr)
