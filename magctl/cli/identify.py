"""``magctl identify LOG… --out DIR``: a rig's run logs → its parameter folder, report and recommended gains."""

from __future__ import annotations

from magctl.cli.common import add_json, emit, existing_file, output_dir


def register(sub) -> None:
    p = sub.add_parser("identify", help="fit the plant to a rig's run logs: a parameter folder, a report, gains",
                       description="Reads run logs written by `magctl rig run` (the identification experiment, "
                                   "`magctl rig experiment`, and any push runs) and writes a complete parameter "
                                   "folder: every value the logs determine, with its uncertainty and source; the "
                                   "rest kept at their defaults and listed with the reason (docs/identify.md).")
    p.add_argument("logs", nargs="+", type=existing_file, metavar="LOG", help="run logs (JSON lines)")
    p.add_argument("--out", type=output_dir, required=True,
                   help="folder to write (new or empty): parameter files, identified.json, report.md, figures")
    p.add_argument("--holdout", nargs="+", type=existing_file, default=[], metavar="LOG",
                   help="run logs kept out of the fit: the report compares the identified plant's predictions with "
                        "what these runs did")
    p.add_argument("--no-report", action="store_true",
                   help="write the parameter folder only (no report, no stability analyses)")
    add_json(p)
    p.set_defaults(func=cmd_identify)


def cmd_identify(args) -> int:
    from magctl.identify.phases import load_runs
    from magctl.identify.report import recommend, validate, write_report
    from magctl.identify.run import identify

    # the held-out logs are read with the fitted ones first: logs of another rig are refused before anything is written
    held = load_runs([*args.logs, *args.holdout])[len(args.logs):] if args.holdout else None
    result = identify(args.logs, args.out)
    recs = validation = None
    if not args.no_report:
        recs = recommend(args.out)
        validation = validate(result, held, recs) if held else None
        write_report(args.out, result, recs, validation)
    doc = {"out": str(args.out), "logs": [str(p) for p in args.logs],
           "identified": {e.name: {"value": e.value, "uncertainty": e.uncertainty, "evidence": e.evidence}
                          for e in result.estimates},
           "not_identified": result.not_identified, "recommendations": recs, "validation": validation,
           "timings_s": result.timings}
    emit(args, doc, _summary)
    return 0


def _summary(d: dict) -> str:
    lines = [f"identified from {len(d['logs'])} log(s) → {d['out']}"]
    for name, e in d["identified"].items():
        lines.append(f"  {name} = {e['value']:.4g} ± {e['uncertainty']:.2g}")
    for what, why in d["not_identified"].items():
        lines.append(f"  not identified: {what}: {why}")
    r = d.get("recommendations")
    if r:
        lines.append(f"  run: {r['run']}")
        lines.append(f"  report: {d['out']}/report.md")
    return "\n".join(lines)
