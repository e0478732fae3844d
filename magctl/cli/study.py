"""``magctl study NAME`` and ``magctl reproduce``."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from magctl.cli.common import add_json, emit, to_jsonable
from magctl.studies import runner as studies
from magctl.studies.report import write_report


def register(sub) -> None:
    p = sub.add_parser("study", help="run one study from analysis/")
    p.add_argument("name", help="study name (magctl study --list shows them)", nargs="?")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    _common(p)
    add_json(p)
    p.set_defaults(func=cmd_study)

    r = sub.add_parser("reproduce", help="run every study and write DIR/report.md and DIR/results.json")
    _common(r)
    r.set_defaults(func=cmd_reproduce)


def _common(p) -> None:
    p.add_argument("--trials", type=int, default=None, help="Monte Carlo trials per controller")
    p.add_argument("--out", type=Path, default=Path("out"), help="output folder (default: out)")
    p.add_argument("--seed", type=int, default=0, help="root seed")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://127.0.0.1:8786")
    p.add_argument("--workers", type=int, default=None, help="local worker processes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-figures", action="store_true", help="compute and summarise only; draw no figures")
    p.add_argument("--fem", action="store_true",
                   help="also run the finite-element models (fig6-domain's COMSOL box; minutes; needs magctl[fem])")


def _context(args, name: str, cache: studies.TrialCache | None = None) -> studies.StudyContext:
    return studies.StudyContext(
        out=args.out / name, trials=args.trials, seed=args.seed, scheduler=args.scheduler,
        workers=args.workers, quiet=args.quiet, fem=args.fem,
        trial_cache=cache if cache is not None else studies.TrialCache(),
    )


def cmd_study(args) -> int:
    if args.list or not args.name:
        for name, module in studies.discover().items():
            print(f"{name:18s} {getattr(module, 'TITLE', '')}")
        return 0
    result = studies.run_study(args.name, _context(args, args.name), figures=not args.no_figures)
    doc = {"study": result.name, **result.results, "figures": [str(f) for f in result.figures]}
    emit(args, doc, lambda _: "\n".join([f"# {result.name}", *result.summary,
                                         *(f"figure: {f}" for f in result.figures)]))
    return 0


def cmd_reproduce(args) -> int:
    found = studies.discover()
    studies.check_reuses(found)
    cache = studies.TrialCache()  # one per run: studies that declare REUSES take trials from it
    results, timings = [], {}
    for name in found:
        if not args.quiet:
            print(f"[reproduce] {name} …", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        results.append(studies.run_study(name, _context(args, name, cache), figures=not args.no_figures))
        timings[name] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {
        "studies": {r.name: r.results for r in results},
        "paper_vs_magctl": [vars(row) | {"study": r.name} for r in results for row in r.paper],
        "wall_time_s": timings,
    }
    (args.out / "results.json").write_text(json.dumps(to_jsonable(doc), indent=2))
    report = write_report(args.out, results, timings)
    print(f"wrote {report} and {args.out / 'results.json'} ({len(results)} studies, "
          f"{sum(timings.values()):.1f} s)")
    return 0
