"""``magctl log show|export|replay|view FILE``: run logs written by ``magctl rig run --log``."""

from __future__ import annotations

import sys

from magctl.cli.common import add_json, emit, existing_file, output_file, positive_float


def register(sub) -> None:
    p = sub.add_parser("log", help="show, export or replay a rig run log")
    ls = p.add_subparsers(dest="log_command", metavar="LOG_COMMAND")
    ls.required = True

    s = ls.add_parser("show", help="summary of a run log")
    s.add_argument("file", type=existing_file, help="run log (JSON lines)")
    add_json(s)
    s.set_defaults(func=cmd_show)

    e = ls.add_parser("export", help="export the events to Parquet (.parquet) or HDF5 (.h5)")
    e.add_argument("file", type=existing_file, help="run log (JSON lines)")
    e.add_argument("--out", type=output_file, required=True, help="output file: .parquet, .h5 or .hdf5")
    add_json(e)
    e.set_defaults(func=cmd_export)

    r = ls.add_parser("replay", help="feed the logged observations through the controller; compare commands")
    r.add_argument("file", type=existing_file, help="run log (JSON lines)")
    add_json(r)
    r.set_defaults(func=cmd_replay)

    v = ls.add_parser("view", help="the replay page of one or more run logs in the browser (needs magctl[view])")
    v.add_argument("files", type=existing_file, nargs="+", metavar="FILE",
                   help="run logs (JSON lines); several are shown side by side")
    v.add_argument("--view", default=None, metavar="HOST:PORT",
                   help="address to serve the page on (default 127.0.0.1:8050; port 0: any free port)")
    v.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="stop serving after S seconds (default: until Ctrl-C)")
    v.set_defaults(func=cmd_view)


def _warn_crashed(note) -> None:
    if note:
        print(f"magctl: warning: {note}", file=sys.stderr)


def cmd_show(args) -> int:
    from magctl.rig.log import read_log

    log = read_log(args.file)
    doc = log.summary()
    emit(args, doc, _show_text)
    _warn_crashed(log.crash_note())
    return 0


_UNIT_TEXT = (("_um_s", "µm/s"), ("_um", "µm"), ("_ms", "ms"), ("_s", "s"))


def _named(key: str) -> tuple[str, str]:
    """``"push_speed_um_s"`` → ``("push_speed", " µm/s")``: the unit suffix of a key as written text."""
    for suffix, text in _UNIT_TEXT:
        if key.endswith(suffix):
            return key[: -len(suffix)], f" {text}"
    return key, ""


def _fmt(v) -> str:
    if isinstance(v, dict):
        return ", ".join(f"{name} {_fmt(x)}{unit}" for name, unit, x in ((*_named(k), x) for k, x in v.items()))
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def _show_text(d: dict) -> str:
    """``log show`` as text: one line per item, units written out (µm, µm/s, ms, s)."""
    lines = []
    for key, value in d.items():
        if key == "note":
            continue
        name, unit = _named(key)
        lines.append(f"{name.replace('_', ' ')}: {_fmt(value)}{unit if value is not None else ''}")
    return "\n".join(lines)


def cmd_export(args) -> int:
    from magctl.rig.log import export, read_log

    log = read_log(args.file)
    out = export(args.file, args.out)
    doc = {"log": str(args.file), "out": str(out), "events": len(log.events), "crashed": log.crashed,
           "complete_to": log.complete_to}
    emit(args, doc, lambda d: f"wrote {d['out']} ({d['events']} events)")
    _warn_crashed(log.crash_note())
    return 0


def cmd_replay(args) -> int:
    from magctl.rig.log import replay

    res = replay(args.file)
    doc = {"log": str(args.file), "events": res.events, "commands_compared": res.compared,
           "mismatches": res.mismatches, "identical": res.identical, "first_mismatch": res.first_mismatch,
           "crashed": res.crashed, "complete_to": res.complete_to}
    emit(args, doc, lambda d: (f"replayed {d['events']} events: {d['commands_compared']} commands compared, "
                               f"{d['mismatches']} mismatches — " + ("identical" if d["identical"] else "DIFFERENT")
                               + (f" (up to event seq {d['complete_to']['seq']}; the log has no stop document)"
                                  if d["crashed"] else "")))
    _warn_crashed(res.note)
    return 0 if res.identical else 1


def cmd_view(args) -> int:
    import time

    from magctl.view.replay import open_runs
    from magctl.view.server import DEFAULT_ADDRESS, ViewServer

    runs = open_runs(args.files)     # a file that is not a run log: its one-line error, before anything is served
    server = ViewServer.replay(runs, args.view or DEFAULT_ADDRESS)
    for run in runs:
        _warn_crashed(run.log.crash_note())
    print(f"magctl log view: {server.url}  ({len(runs)} run{'s' * (len(runs) > 1)}; Ctrl-C to stop)",
          file=sys.stderr, flush=True)
    try:
        end = None if args.duration is None else time.monotonic() + args.duration
        while end is None or time.monotonic() < end:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0
