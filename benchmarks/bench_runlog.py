"""The run log's cost per frame: checking an event document against the schema, and writing and reading one.

Every document is checked when written and when read (``magctl.rig.log.schema_error``): a compiled check
(``fastjsonschema``) per document kind, with ``jsonschema`` only to word the reason of a refused one. Measured on
the events of a real side-push run (two spheres, the in-process simulated rig): the check, ``jsonschema``'s full
validation of the same documents (what every document cost before), one event written (check, encode, write,
flush) and one read back (``read_log``, which parses and checks every line). Target: a written event costs at
most 1 ms, 3 % of a 30 Hz frame.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

from rows import fmt, row

TARGET_WRITE_MS = 1.0


def _command(wire):
    from magctl.rig import protocol as P

    return None if wire is None else P.command_from_wire(wire)


def _per_doc_us(fn, docs, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for d in docs:
            fn(d)
        best = min(best, time.perf_counter() - t0)
    return best / len(docs) * 1e6


def run(quick: bool = False) -> dict:
    import jsonschema

    from magctl.rig.log import SCHEMA, RunLogWriter, event_observation, read_log, schema_error
    from magctl.rig.runtime import Runtime
    from magctl.rig.sim import SimRig

    ticks = 150 if quick else 600
    repeat = 3 if quick else 7
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "run.jsonl"
        Runtime(SimRig(n_spheres=2), "side-push", {}, log_path=path, realtime=False, max_ticks=ticks,
                quiet=True).run()
        docs = [json.loads(line) for line in path.read_text().splitlines()]
        events = [d for d in docs if d["doc"] == "event"]
        reference = jsonschema.Draft202012Validator(SCHEMA)
        check_us = _per_doc_us(schema_error, events, repeat)
        jsonschema_us = _per_doc_us(reference.is_valid, events, repeat)

        frames = [(d["seq"], event_observation(d), _command(d["cmd_raw"]), _command(d["cmd"]), d["outputs"],
                   d["timing"], d["activation"]) for d in events]
        start = {k: v for k, v in docs[0].items() if k not in ("doc", "format", "uid", "time_unix", "magctl_version")}
        write_ms = float("inf")
        for k in range(repeat):
            writer = RunLogWriter(Path(tmp) / f"copy{k}.jsonl", max_bytes=0)
            writer.start(**start)
            writer.descriptor(docs[1]["fields"])
            t0 = time.perf_counter()
            for frame in frames:
                writer.event(*frame)
            write_ms = min(write_ms, (time.perf_counter() - t0) / len(frames) * 1e3)
            writer.stop("done", "benchmark")
        read_ms = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            read_log(path)
            read_ms = min(read_ms, (time.perf_counter() - t0) / len(events) * 1e3)
    return {
        "events": len(events),
        "check_us_per_event": check_us,
        "jsonschema_us_per_event": jsonschema_us,
        "speedup": jsonschema_us / check_us,
        "write_ms_per_event": write_ms,
        "read_ms_per_event": read_ms,
        "target_write_ms": TARGET_WRITE_MS,
        "met": write_ms <= TARGET_WRITE_MS,
        "rows": [
            row("run log: one event written (schema check, encode, write, flush)", write_ms, "ms",
                le=TARGET_WRITE_MS, note=f"read back {fmt(read_ms)} ms per event; {len(events)} events of a "
                                         f"side push, best of {repeat}"),
            row("run log: schema check of one event, compiled (fastjsonschema)", check_us, "µs",
                le=jsonschema_us, note=f"jsonschema's validation of the same events {fmt(jsonschema_us)} µs "
                                       f"({fmt(jsonschema_us / check_us)}×)"),
        ],
    }


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
