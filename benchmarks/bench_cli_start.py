"""Start-up time of the ``magctl`` command: ``magctl --help`` in a fresh interpreter (target ≤ 0.5 s).

The command builds its parser from the subcommand modules, which import their computing code
(python-control, scipy, matplotlib, numba) only inside the commands. What is measured is the wall
time of whole processes, as a user sees it: the best and the median of several runs, next to the
start-up of a bare ``python -c pass`` on the same machine, and which heavy modules the help
imported (none should be).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rows import fmt, row

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 0.5
HEAVY = ("numpy", "control", "scipy", "matplotlib", "numba", "magpylib", "zmq", "distributed")


def _wall(args: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def run(quick: bool = False) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    n = 5 if quick else 15
    help_cmd = [sys.executable, "-m", "magctl", "--help"]
    _wall(help_cmd, env)                                          # warm the file cache
    helps = [_wall(help_cmd, env) for _ in range(n)]
    bare = [_wall([sys.executable, "-c", "pass"], env) for _ in range(n)]
    probe = ("import sys; from magctl.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             f"print('HEAVY:' + ','.join(m for m in {HEAVY!r} if m in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    marker = [line for line in loaded.stdout.splitlines() if line.startswith("HEAVY:")][-1]
    heavy = [m for m in marker.removeprefix("HEAVY:").split(",") if m]
    best, median = min(helps), statistics.median(helps)
    return {
        "help_best_s": best,
        "help_median_s": median,
        "python_bare_median_s": statistics.median(bare),
        "heavy_modules_imported_by_help": heavy,
        "runs": n,
        "target_s": TARGET_S,
        "met": median <= TARGET_S and not heavy,
        "rows": [
            row("`magctl --help` in a fresh interpreter, median wall time", median, "s", le=TARGET_S,
                note=f"best {fmt(best)} s of {n}; bare `python -c pass` {fmt(statistics.median(bare))} s"),
            row("heavy modules (numpy, scipy, numba, …) imported by `magctl --help`", len(heavy), "modules", le=0,
                note=", ".join(heavy)),
        ],
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
