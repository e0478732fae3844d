"""``magctl study NAME`` and ``magctl reproduce``."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from magctl.cli.common import (
    add_json,
    contact_scheduler,
    emit,
    output_dir,
    positive_int,
    scheduler_address,
    seed,
    to_jsonable,
)


def register(sub) -> None:
    p = sub.add_parser("study", help="run one study from analysis/")
    p.add_argument("name", help="study name (magctl study --list shows them)", nargs="?")
    p.add_argument("--list", action="store_true", help="list the studies and exit")
    _common(p)
    add_json(p)
    p.set_defaults(func=cmd_study, parser=p)

    r = sub.add_parser("reproduce",
                       help="run every study and write DIR/report.md, DIR/report.html and DIR/results.json")
    r.add_argument("--only", nargs="+", metavar="NAME", default=None,
                   help="run only these studies (magctl study --list shows them)")
    _common(r)
    r.set_defaults(func=cmd_reproduce, parser=r)


def _common(p) -> None:
    p.add_argument("--trials", type=positive_int, default=None, help="Monte Carlo trials per controller (>= 1)")
    p.add_argument("--out", type=output_dir, default=Path("out"), help="output folder (default: out)")
    p.add_argument("--seed", type=seed, default=0, help="root seed (integer >= 0)")
    p.add_argument("--scheduler", type=scheduler_address, default=None,
                   help="Dask scheduler address, e.g. tcp://127.0.0.1:8786 (contacted before any study runs)")
    p.add_argument("--workers", type=positive_int, default=None, help="local worker processes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-figures", action="store_true", help="compute and summarise only; draw no figures")
    p.add_argument("--fem", action="store_true",
                   help="also run the finite-element models (fig6-domain's COMSOL box; minutes; needs magctl[fem])")
    p.add_argument("--conditions", choices=("magctl", "paper"), default="magctl",
                   help="controllers as magctl runs them (default) or as the paper did: its overshooting servo, "
                        "printed eq 22/23, 370 µm bound, 650 µm clearance, δ(0) = 127 µm")


def _context(args, name: str, cache=None):
    from magctl.studies import runner as studies

    return studies.StudyContext(
        out=args.out / name, trials=args.trials, seed=args.seed, scheduler=args.scheduler,
        workers=args.workers, quiet=args.quiet, fem=args.fem,
        trial_cache=cache if cache is not None else studies.TrialCache(), conditions=args.conditions,
    )


def cmd_study(args) -> int:
    from magctl.studies import runner as studies

    if args.list or not args.name:
        for name, module in studies.discover().items():
            print(f"{name:18s} {getattr(module, 'TITLE', '')}")
        return 0
    studies.get(args.name)  # an unknown name is an error before the scheduler is contacted
    contact_scheduler(args.parser, args.scheduler)
    _say(args, f"[study] {args.name} …")
    t0 = time.perf_counter()
    result = studies.run_study(args.name, _context(args, args.name), figures=not args.no_figures)
    _say(args, f"[study] {args.name} done in {time.perf_counter() - t0:.1f} s")
    doc = {"study": result.name, **result.results, "figures": [str(f) for f in result.figures]}
    emit(args, doc, lambda _: "\n".join([f"# {result.name}", *result.summary,
                                         *(f"figure: {f}" for f in result.figures)]))
    return 0


def cmd_reproduce(args) -> int:
    from magctl.studies import runner as studies
    from magctl.studies.report import write_report
    from magctl.studies.report_html import write_html_report

    found = studies.discover()
    studies.check_reuses(found)
    if args.only:
        unknown = [name for name in args.only if name not in found]
        if unknown:
            args.parser.error(f"argument --only: no study {', '.join(map(repr, unknown))}; "
                              f"studies: {', '.join(found)}")
        found = {name: module for name, module in found.items() if name in args.only}
    else:
        found = studies.reproduced(found)
    contact_scheduler(args.parser, args.scheduler)
    cache = studies.TrialCache()  # one per run: studies that declare REUSES take trials from it
    results, timings = [], {}
    for k, name in enumerate(found, 1):
        _say(args, f"[reproduce {k}/{len(found)}] {name} …")
        t0 = time.perf_counter()
        results.append(studies.run_study(name, _context(args, name, cache), figures=not args.no_figures))
        timings[name] = time.perf_counter() - t0
        _say(args, f"[reproduce {k}/{len(found)}] {name} done in {timings[name]:.1f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    # results.json holds only what the trials computed, so two runs (any executor) give the same bytes;
    # the wall times go beside it
    doc = {
        "studies": {r.name: r.results for r in results},
        "paper_vs_magctl": [vars(row) | {"study": r.name} for r in results for row in r.paper],
    }
    (args.out / "results.json").write_text(json.dumps(to_jsonable(doc), indent=2))
    (args.out / "timings.json").write_text(json.dumps({"wall_time_s": timings}, indent=2))
    report = write_report(args.out, results, timings, conditions=args.conditions)
    page = write_html_report(args.out, results, timings, conditions=args.conditions)
    print(f"wrote {report}, {page}, {args.out / 'results.json'} and timings.json ({len(results)} studies, "
          f"{sum(timings.values()):.1f} s)")
    return 0


def _say(args, line: str) -> None:
    """One progress line per study on stderr (the trial bars are shown only on a terminal)."""
    if not args.quiet:
        print(line, file=sys.stderr, flush=True)
