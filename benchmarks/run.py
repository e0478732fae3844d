"""``make bench``: run every ``benchmarks/bench_*.py`` and write one dated JSON file.

Each benchmark module defines ``run(quick: bool = False) -> dict``; its numbers
(with targets and whether they were met) go into the JSON under its name, beside a ``meta``
block: the date, the commit measured (``+dirty`` when the tree had uncommitted changes), the
machine's cores and numpy's small-op cost before the run. The file is
``benchmarks/results/<date>-<commit>.json``; committed, it is what docs/benchmarks.md's
table is generated from (``benchmarks/readme.py``). Every
``bench_*.py`` here is picked up; the rig's (``rig_soak``, ``rig_fuzz``, ``rig_watchdog``)
start ``serve-sim`` processes on loopback and take minutes each (``--only`` to pick); those in
:data:`OPT_IN` (the finite-element box) run only when named with ``--only``.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

OPT_IN = {"fem_box": "the finite-element box model (needs the fem extra, ~15 min cold): --only fem_box"}
"""Benchmarks run only when named with ``--only``."""


def small_op_us() -> float:
    """Best time of one small numpy operation (a 100-element add) [µs]: how fast this machine is right now.

    Most of the loops measured here are bound by the fixed cost of numpy calls, so runs on a
    shared machine are comparable only next to this number.
    """
    import timeit

    import numpy as np

    a = np.ones(100)
    return min(timeit.repeat(lambda: a + a, number=20000, repeat=7)) / 20000 * 1e6


def commit() -> str:
    """The commit measured: ``git rev-parse --short HEAD``, ``+dirty`` with uncommitted changes to tracked files."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=HERE, capture_output=True, text=True, check=False).stdout.strip()

    head = git("rev-parse", "--short=10", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=None, help="default: benchmarks/results/<date>-<commit>.json")
    parser.add_argument("--only", nargs="*", help="benchmark names (e.g. b1_servo_loop)")
    parser.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    args = parser.parse_args()
    sys.path.insert(0, str(HERE))
    now = datetime.datetime.now(datetime.UTC)
    meta = {"date": now.strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit(), "cores": os.cpu_count(),
            "python": platform.python_version(), "platform": platform.platform(), "numpy_small_op_us": small_op_us(),
            "quick": bool(args.quick), "only": args.only or None}
    if args.out is None:
        args.out = HERE / "results" / f"{now:%Y-%m-%d}-{meta['commit'].replace('+', '-')}.json"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    results = {"meta": meta}
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if args.only and name not in args.only:
            continue
        if name in OPT_IN and not (args.only and name in args.only):
            results[name] = {"skipped": f"opt-in: {OPT_IN[name]}"}
            continue
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        print(f"[bench] {name} …", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        results[name] = module.run(quick=args.quick)
        results[name]["wall_time_s"] = time.perf_counter() - t0
        results[name]["numpy_small_op_us"] = small_op_us()   # right after, under the same load
        print(json.dumps({name: results[name]}, indent=2, default=float))
        # written after every benchmark, so a later one that fails loses none of the numbers before it
        args.out.write_text(json.dumps(results, indent=2, default=float))
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
