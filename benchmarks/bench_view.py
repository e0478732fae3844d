"""The live view's cost to the 30 Hz loop: tick jitter and overruns of a real-time run with and without ten pages.

Real-time side pushes on the in-process simulated rig (``Runtime(SimRig(realtime=True))``, as ``magctl rig run
--rig sim --task side-push``), ``ticks`` ticks each, alternately without a view and with ``--view``'s server and
ten pages connected from another process (as browsers are): nine read every frame they are sent (30/s), one
connects with a 4 KiB receive buffer and never reads. The runs alternate (without, with, without, with) so that
the machine's load falls on both alike.

Targets: with the pages, no more overruns than without, and the tick jitter's p99 within 1 ms of the run without
(the view only hands each frame's document to the feed; the server's thread does the encoding and sending).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
from rows import fmt, row

PAGES = 10

CLIENTS = textwrap.dedent('''
    import json, socket, sys, threading, time
    from websockets.sync.client import connect
    port, seconds = int(sys.argv[1]), float(sys.argv[2])
    url = f"ws://127.0.0.1:{port}/ws"
    counts = [0] * 9
    last = [-1] * 9
    def reader(k):
        end = time.monotonic() + seconds
        with connect(url) as ws:
            while time.monotonic() < end:
                try:
                    doc = json.loads(ws.recv(timeout=1))
                except TimeoutError:
                    continue
                except Exception:
                    return
                counts[k] += 1
                if doc.get("event"):
                    last[k] = doc["event"]["seq"]
                if doc["type"] == "stopped":
                    return
    sleeper = socket.create_connection(("127.0.0.1", port))
    sleeper.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    never = connect(url, sock=sleeper)
    threads = [threading.Thread(target=reader, args=(k,)) for k in range(9)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(json.dumps({"messages": counts, "last_seq": last}))
''')


def _run(ticks: int, folder: Path, k: int, pages: bool) -> dict:
    from magctl.rig.runtime import Runtime
    from magctl.rig.sim import SimRig
    from magctl.view.feed import LiveFeed
    from magctl.view.server import ViewServer

    feed = server = clients = None
    if pages:
        feed = LiveFeed()
        server = ViewServer.live(feed, "127.0.0.1:0")
        clients = subprocess.Popen([sys.executable, "-c", CLIENTS, str(server.port), str(ticks / 30 + 30)],
                                   stdout=subprocess.PIPE, text=True)
        time.sleep(2.0)     # the pages connect before the run starts
    try:
        report = Runtime(SimRig(n_spheres=1, realtime=True, seed=k), "side-push", {}, realtime=True, seed=k,
                         max_ticks=ticks, log_path=folder / f"run{k}.jsonl", quiet=True, monitor=feed).run()
    finally:
        if server is not None:
            server.close()
    out = {"ticks": report.ticks, "overruns": report.overruns,
           "jitter_ms": {q: float(np.percentile(report.jitter, q) * 1e3) for q in (50, 99)}
           | {"max": float(report.jitter.max() * 1e3)},
           "compute_p99_ms": float(np.percentile(report.compute, 99) * 1e3)}
    if clients is not None:
        got = json.loads(clients.communicate(timeout=120)[0])
        out["pages"] = {"reading": 9, "never_reading": 1, "messages_min": min(got["messages"]),
                        "messages_max": max(got["messages"]), "last_seq_min": min(got["last_seq"])}
    return out


def run(quick: bool = False) -> dict:
    ticks = 150 if quick else 900
    runs = {"without": [], "with": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(2):
            runs["without"].append(_run(ticks, Path(tmp), 2 * k, pages=False))
            runs["with"].append(_run(ticks, Path(tmp), 2 * k + 1, pages=True))

    def worst(key, sub=None):
        return {m: max(r[key] if sub is None else r[key][sub] for r in runs[m]) for m in runs}

    p99, overruns, jmax = worst("jitter_ms", 99), worst("overruns"), worst("jitter_ms", "max")
    pages = [r["pages"] for r in runs["with"]]
    out = {"ticks": ticks, "pages": PAGES, "runs": runs}
    out["rows"] = [
        row("live view: tick jitter p99 with 10 pages (one never reading) minus without", p99["with"] - p99["without"],
            "ms", le=1.0, note=f"p99 {fmt(p99['with'])} ms with, {fmt(p99['without'])} ms without (worst of 2 "
                                f"real-time side pushes of {ticks} ticks each); max {fmt(jmax['with'])} / "
                                f"{fmt(jmax['without'])} ms"),
        row("live view: overruns with 10 pages minus without", overruns["with"] - overruns["without"], "ticks", le=0,
            note=f"{overruns['with']} with, {overruns['without']} without; the reading pages got "
                 f"{min(p['messages_min'] for p in pages)}-{max(p['messages_max'] for p in pages)} frames each, "
                 f"the last at seq ≥ {min(p['last_seq_min'] for p in pages)} of {ticks - 1}"),
    ]
    out["all_met"] = all(r["met"] for r in out["rows"])
    return out


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
