"""Protocol fuzzing of ``magctl rig serve-sim`` on loopback at ≥ 100 000 messages (not a CI test).

Two servers, each its own process as a user starts it: lock-step (watchdog checked in simulated
time, exact) and real time (the coil guard's wall-clock watchdog, frozen and half-sent peers
connected during every silence), each with 20 concurrent stranger clients flooding it beside the
fuzzer (``magctl.rig.fuzz``). Targets (issue: rig safety under any bytes): 0 server exits, 0
invalid commands applied, 0 unanswered or malformed replies, every watchdog trip within
100 ms + one frame. ``run(quick=True)``: 5 000 messages each.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

from rows import row

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT / "tests" / "rig"))

N_FULL = 100_000
N_CROWD = 20


def _one(mode: str, n: int) -> dict:
    from rig_helpers import ServerProcess

    from magctl.config import load_model
    from magctl.rig.fuzz import crowd, fuzz

    params = load_model("rig")
    period, watchdog = 1.0 / params.runtime.rate, params.watchdog.timeout
    srv = ServerProcess(*(["--lockstep"] if mode == "lockstep" else []), "--plant", "standin")
    stop = threading.Event()
    try:
        crowd_run = crowd(srv.address, N_CROWD, stop, seed=3, max_messages=n)
        t0 = time.monotonic()
        rep = fuzz(srv.address, n, seed=11, lockstep=mode == "lockstep", time_budget=1800.0,
                   alive=lambda: srv.proc.poll() is None, watchdog=watchdog, period=period)
        stop.set()
        for t in crowd_run["threads"]:
            t.join(timeout=30)
        elapsed = time.monotonic() - t0
        alive = srv.proc.poll() is None
    finally:
        stop.set()
        srv.kill()
    d = rep.to_dict()
    c = crowd_run["counts"]
    measured = {
        "messages_fuzzer": rep.messages, "messages_crowd": c["messages"],
        "messages_total": rep.messages + c["messages"],
        "elapsed_s": elapsed, "server_exits": rep.server_exits + (0 if alive else 1),
        "invalid_applied": rep.invalid_applied + c["accepted_writes"],
        "unanswered": rep.unanswered + c["unanswered"], "malformed_replies": rep.malformed_replies + c["malformed"],
        "watchdog_checked": rep.watchdog_checked, "watchdog_late": rep.watchdog_late,
        "watchdog_after_ms": d.get("watchdog_after_ms"), "accepted_writes": rep.accepted_writes,
        "server_applied": rep.server_applied, "error_codes": rep.error_codes, "by_channel": rep.by_channel,
        "failures": rep.failures[:5],
    }
    met = {"messages": measured["messages_total"] >= n, "server_exits": measured["server_exits"] == 0,
           "invalid_applied": measured["invalid_applied"] == 0 and rep.server_applied == rep.accepted_writes,
           "replies": measured["unanswered"] == 0 and measured["malformed_replies"] == 0,
           "watchdog": rep.watchdog_late == 0 and rep.watchdog_checked > 0}
    return {"measured": measured, "met": met}


def run(quick: bool = False) -> dict:
    n = 5000 if quick else N_FULL
    out = {mode: _one(mode, n) for mode in ("lockstep", "realtime")}
    met = {f"{mode}_{k}": v for mode, r in out.items() for k, v in r["met"].items()}
    return {**out, "targets": {"messages_each": n, "server_exits": 0, "invalid_applied": 0, "unanswered": 0,
                               "watchdog_after_ms_max": "100 + one frame (133.3)"},
            "met": met, "all_met": all(met.values()), "load_avg_1min": os.getloadavg()[0],
            "rows": _rows(out, n)}


def _rows(out: dict, n: int) -> list[dict]:
    """The table's rows, per mode: messages, server exits, invalid commands applied, replies, watchdog."""
    import math

    from magctl.config import load_model

    params = load_model("rig")
    # the fuzzer's own bound: 100 ms + one frame, and 1 ns for the float sums of lock-step time's frames
    bound_ms = (params.watchdog.timeout + 1.0 / params.runtime.rate + 1e-9) * 1e3
    rows = []
    for mode, label, clock in (("lockstep", "lock-step", "simulated time"), ("realtime", "real time", "wall clock")):
        m = out[mode]["measured"]
        name = f"rig protocol fuzzer, {label}, beside {N_CROWD} flooding clients"
        after = m["watchdog_after_ms"] or {}
        applied = m["server_applied"]
        rows += [
            row(f"{name}: messages sent by the fuzzer", m["messages_fuzzer"], "messages", ge=n,
                note=f"{m['messages_crowd']:,} more from the flooding clients"),
            row(f"{name}: server exits", m["server_exits"], "exits", le=0),
            row(f"{name}: invalid commands applied", m["invalid_applied"], "commands", le=0,
                note="the fuzzer's invalid commands the server applied, and any stranger's write it accepted"),
            row(f"{name}: commands the server applied beyond the owner's accepted writes",
                math.nan if applied is None else abs(applied - m["accepted_writes"]), "commands", le=0,
                note=f"{m['accepted_writes']:,} accepted writes"),
            row(f"{name}: unanswered or malformed replies", m["unanswered"] + m["malformed_replies"], "replies",
                le=0),
            row(f"{name}: coil watchdog, slowest trip after the last valid command ({clock})", after.get("max"), "ms",
                le=bound_ms, note=f"p99 {after['p99']:.4g} ms of {after['n']:,} trips" if after else "no trip seen"),
            row(f"{name}: rounds whose watchdog trip was late, early or missing", m["watchdog_late"], "rounds", le=0,
                note=f"of {m['watchdog_checked']:,} trips checked"),
        ]
    return rows


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=str))
