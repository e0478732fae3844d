"""``magctl bench``: run the benchmarks in ``benchmarks/`` (same as ``make bench``)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from magctl.cli.common import output_file
from magctl.core.errors import MagctlError

RUNNER = Path(__file__).resolve().parents[2] / "benchmarks" / "run.py"
"""The benchmark runner of a source checkout (benchmarks/ is not part of the wheel)."""


def available() -> list[str]:
    """Names of the benchmarks beside the runner (``bench_NAME.py`` → ``NAME``)."""
    return sorted(p.stem.removeprefix("bench_") for p in RUNNER.parent.glob("bench_*.py"))


def register(sub) -> None:
    p = sub.add_parser("bench", help="run the benchmarks in benchmarks/ and write JSON")
    p.add_argument("--only", nargs="*", help="benchmark names, e.g. b1_servo_loop")
    p.add_argument("--quick", action="store_true", help="smaller sizes")
    p.add_argument("--out", type=output_file, default=None,
                   help="JSON file (default benchmarks/results/<date>-<commit>.json)")
    p.add_argument("--json", action="store_true", help="print the JSON results on stdout")
    p.set_defaults(func=cmd_bench, parser=p)


def cmd_bench(args) -> int:
    runner = RUNNER
    if not runner.is_file():
        raise MagctlError(f"benchmark runner {runner} not found: benchmarks/ ships with the source tree, "
                          f"not with the wheel; run magctl bench in a checkout")
    unknown = sorted(set(args.only or ()) - set(available()))
    if unknown:
        args.parser.error(f"argument --only: no benchmark {', '.join(map(repr, unknown))}; "
                          f"benchmarks: {', '.join(available())}")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or (Path(tmp) / "results.json" if args.json else None)
        cmd = [sys.executable, str(runner)] + (["--out", str(out)] if out else [])
        if args.only:
            cmd += ["--only", *args.only]
        if args.quick:
            cmd.append("--quick")
        done = subprocess.run(cmd, stdout=subprocess.DEVNULL if args.json else None, check=False)
        if done.returncode:
            raise MagctlError(f"benchmarks failed (exit {done.returncode})")
        if args.json:
            print(out.read_text())
    return 0
