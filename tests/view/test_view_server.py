"""The view's server without a browser: what it serves, and what it does with bad input and slow or hostile pages.

Runs go in process on a ``SimRig``; the pages are ``websockets`` clients speaking to the real uvicorn server.
Nothing here asserts time: a stalled run would show as a run that never reaches its tick count.
"""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from view_helpers import ROOT, MagctlProcess

from magctl.rig.log import LogError, read_log, replay
from magctl.rig.monitor import RunControls
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig
from magctl.sensing.camera import field_of_view
from magctl.view.feed import LiveFeed
from magctl.view.replay import ReplayRun
from magctl.view.server import ViewError, ViewServer

ws_client = pytest.importorskip("websockets.sync.client", reason="the view extra installs websockets")
ConnectionClosed = pytest.importorskip("websockets.exceptions").ConnectionClosed


def get_json(url: str):
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def side_push_log(path, ticks=None, seed=0):
    Runtime(SimRig(n_spheres=1, seed=seed), "side-push", {}, log_path=path, realtime=False, seed=seed,
            max_ticks=ticks or 3000, quiet=True).run()
    return path


def live_run(tmp_path, ticks, controls=None, address="127.0.0.1:0", realtime=True):
    """A side push running on a thread with its live view; returns (server, thread, result dict, log path)."""
    feed = LiveFeed()
    server = ViewServer.live(feed, address, controls)
    log = tmp_path / "live.jsonl"
    out = {}

    def go():
        out["report"] = Runtime(SimRig(n_spheres=1, realtime=realtime), "side-push", {}, log_path=log,
                                realtime=realtime, max_ticks=ticks, quiet=True, monitor=feed,
                                controls=controls).run()

    thread = threading.Thread(target=go)
    return server, thread, out, log, feed


def ws_url(server) -> str:
    return f"ws://127.0.0.1:{server.port}/ws"


# --- the scene and the replay index ---------------------------------------------------------------------------
def test_the_scene_comes_from_the_runs_own_parameter_files(tmp_path):
    run = ReplayRun(side_push_log(tmp_path / "a.jsonl", ticks=30))
    scene = run.scene
    assert scene["field_m"] == pytest.approx(list(field_of_view()), rel=1e-12)
    outline = np.array(scene["robot"]["outline_m"])
    # the paper's 310 × 480 µm star, 310 µm along the heading (§II, §IV-D), its concave face ahead
    assert np.ptp(outline, axis=0) == pytest.approx([310e-6, 480e-6], rel=1e-12)
    assert (scene["robot"]["length_m"], scene["robot"]["width_m"]) == pytest.approx((310e-6, 480e-6))
    front = outline[outline[:, 0] > 0]
    assert front[np.abs(front[:, 1]) < 50e-6, 0].max() < 155e-6 - 60e-6
    assert scene["sphere_radius_m"] == pytest.approx(105e-6)
    opts = run.log.start["options"]
    assert scene["goal_m"] == opts["goal_m"] and scene["eps_m"] == opts["eps_m"]
    assert scene["contact_m"] == opts["min_gap_m"]
    assert scene["coil_limit_A"] == run.log.start["limits"]["coil_current_limit_A"]
    # a run logged with another camera file is drawn with its own field
    start = dict(run.log.start)
    start["models_toml"] = dict(start["models_toml"])
    start["models_toml"]["camera.toml"] = start["models_toml"]["camera.toml"].replace(
        "width_px = { value = 640,", "width_px = { value = 1280,")
    from magctl.view.scene import scene_of

    assert scene_of(start)["field_m"][0] == pytest.approx(1279 * 7.5e-6)
    # … and with its own robot and sphere
    start["models_toml"]["robot_geometry.toml"] = start["models_toml"]["robot_geometry.toml"].replace(
        "length_um = { value = 310.0,", "length_um = { value = 400.0,")
    start["models_toml"]["sphere.toml"] = start["models_toml"]["sphere.toml"].replace(
        "radius_um = { value = 105.0,", "radius_um = { value = 50.0,")
    other = scene_of(start)
    assert np.ptp(np.array(other["robot"]["outline_m"])[:, 0]) == pytest.approx(400e-6)
    assert other["sphere_radius_m"] == pytest.approx(50e-6)


def test_attempt_rows_are_the_goal_distance_where_the_attempt_counter_steps(tmp_path):
    run = ReplayRun(side_push_log(tmp_path / "a.jsonl"))
    goal = run.log.start["options"]["goal_m"]
    steps = [(b["seq"], b["outputs"]["attempt"], b["obs"]["spheres_est_m"])
             for a, b in zip(run.log.events, run.log.events[1:], strict=False)
             if b["outputs"]["attempt"] > a["outputs"]["attempt"]]
    assert len(steps) >= 2
    assert [r["seq"] for r in run.attempts] == [s[0] for s in steps]
    assert [r["attempt"] for r in run.attempts] == [int(s[1]) for s in steps]
    for row, (_, _, spheres) in zip(run.attempts, steps, strict=True):
        assert row["error_m"] == min(math.dist(s, goal) for s in spheres)


def test_passes_are_the_motion_lines_from_where_the_pass_phase_begins_to_its_target(tmp_path):
    from magctl.control.push.side import SidePushTask

    run = ReplayRun(side_push_log(tmp_path / "a.jsonl"))
    pass_code = next(k for k, v in SidePushTask.PHASES.items() if v == "pass")
    ev = run.log.events
    begins = [b for a, b in zip(ev, ev[1:], strict=False)
              if b["outputs"]["phase"] == pass_code and a["outputs"]["phase"] != pass_code]
    assert len(begins) >= len(run.attempts) >= 2
    assert [p["seq"] for p in run.passes] == [b["seq"] for b in begins]
    for p, b in zip(run.passes, begins, strict=True):
        assert p["start_m"] == b["obs"]["robot_est_m"] and p["end_m"] == b["outputs"]["target"]
        # the robot then drives along it: at the pass's last frame it is nearer the end than where it began
        last = next(e for e in ev if e["seq"] > p["seq"] and e["outputs"]["phase"] != pass_code)
        assert math.dist(last["obs"]["robot_est_m"], p["end_m"]) < 0.5 * math.dist(p["start_m"], p["end_m"])


def test_the_series_is_decimated_to_its_cap_and_keeps_the_last_frame(tmp_path, monkeypatch):
    import magctl.view.replay as replay_mod

    run = ReplayRun(side_push_log(tmp_path / "a.jsonl", ticks=500))
    monkeypatch.setattr(replay_mod, "SERIES_POINTS", 64)
    series = run.series()
    assert len(series["index"]) <= 65 and series["index"][0] == 0 and series["index"][-1] == 499
    assert series["points"][-1][0] == run.log.events[-1]["obs"]["t_s"]
    assert run.frames(490, 5000) == run.log.events[490:]


# --- bad input ---------------------------------------------------------------------------------------------------
def test_a_file_that_is_not_a_run_log_is_one_line(tmp_path):
    bad = tmp_path / "notes.txt"
    bad.write_text("hello\n")
    proc = subprocess.run([sys.executable, "-m", "magctl", "log", "view", str(bad), "--view", "127.0.0.1:0"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("magctl: error:") and "notes.txt" in lines[0]


def test_a_torn_log_is_shown_up_to_its_last_whole_line_with_the_note(tmp_path):
    log = side_push_log(tmp_path / "a.jsonl", ticks=60)
    text = log.read_text().splitlines(keepends=True)
    log.write_text("".join(text[:-2]) + text[-2][: len(text[-2]) // 2])     # drop the stop, tear an event
    run = ReplayRun(log)
    info = run.info()
    assert info["n_events"] == 59 and "no stop document" in info["note"] and "torn" in info["note"]
    view = MagctlProcess("log", "view", str(log), "--view", "127.0.0.1:0", "--duration", "60")
    try:
        url = view.url()
        assert get_json(url + "api/info")["runs"][0]["n_events"] == 59
    finally:
        view.kill()
    assert any("no stop document" in line for line in view.lines)
    # torn inside its start document: nothing to show, one line
    head = tmp_path / "head.jsonl"
    head.write_text(text[0][:40])
    with pytest.raises(LogError, match="start document is torn"):
        ReplayRun(head)


def test_a_taken_port_is_one_line_before_anything_moves(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        log = tmp_path / "never.jsonl"
        proc = subprocess.run([sys.executable, "-m", "magctl", "rig", "run", "--rig", "sim", "--task", "side-push",
                               "--view", f"127.0.0.1:{port}", "--log", str(log)], cwd=ROOT, capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode == 2
        assert proc.stderr.strip() == f"magctl: error: view address 127.0.0.1:{port}: Address already in use"
        assert not log.exists()
        with pytest.raises(ViewError, match="Address already in use"):
            ViewServer.replay([], f"127.0.0.1:{port}")
    for bad, why in (("127.0.0.1:http", "the port must be a number"), ("127.0.0.1:70000", "not in 0-65535")):
        with pytest.raises(ViewError, match=why):
            ViewServer.live(LiveFeed(), bad)


def test_without_the_extra_the_view_says_what_to_install(monkeypatch, capsys):
    from magctl.cli import main

    monkeypatch.setitem(sys.modules, "uvicorn", None)
    assert main(["rig", "run", "--rig", "sim", "--task", "side-push", "--view"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("magctl: error: the view needs the 'view' extra: pip install 'magctl[view]' (in a magctl "
                   "checkout: .venv/bin/pip install -e '.[view]')")
    assert main(["rig", "run", "--rig", "sim", "--task", "side-push", "--view-controls"]) == 2
    assert "--view-controls: needs --view" in capsys.readouterr().err


# --- hostile and slow pages ---------------------------------------------------------------------------------------
def test_garbage_on_the_socket_is_ignored_and_never_stops_the_run(tmp_path):
    controls = RunControls()
    server, thread, out, log, feed = live_run(tmp_path, ticks=150, controls=controls)
    thread.start()
    try:
        while feed.latest is None:
            time.sleep(0.01)
        with ws_client.connect(ws_url(server)) as bad:
            for junk in (b"\x00\xff\x10binary", "not json", "[1, 2, 3]", '{"action": "launch"}',
                         '{"action": 5}', '{"rate": 1e9}', '{"rate": "fast"}', "{" * 5000, '"stop"'):
                bad.send(junk)
        with ws_client.connect(ws_url(server), max_size=None) as huge:
            huge.send("x" * 100_000)               # over the 64 KiB cap: this connection is closed
            with pytest.raises(ConnectionClosed) as closed:
                for _ in range(1000):
                    huge.recv(timeout=10)
            assert closed.value.rcvd.code == 1009         # "message too big"
        with ws_client.connect(ws_url(server)) as good:
            seqs = []
            while len(seqs) < 5:
                doc = json.loads(good.recv(timeout=10))
                if doc.get("event"):
                    seqs.append(doc["event"]["seq"])
        thread.join(timeout=120)
    finally:
        server.close()
    assert out["report"].exit_status == "stopped" and out["report"].ticks == 150
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    assert not any("control" in e or e.get("paused") for e in read_log(log).events)


def test_ten_pages_one_never_reading_do_not_stall_the_run(tmp_path):
    server, thread, out, log, feed = live_run(tmp_path, ticks=240)
    thread.start()
    got = [[] for _ in range(9)]
    stop = threading.Event()

    def reader(k):
        with ws_client.connect(ws_url(server)) as ws:
            while not stop.is_set():
                try:
                    doc = json.loads(ws.recv(timeout=1))
                except TimeoutError:
                    continue
                except Exception:   # noqa: BLE001 - the server closed: the run is over
                    return
                got[k].append(doc)
                if doc["type"] == "stopped":
                    return

    sleeper = socket.create_connection(("127.0.0.1", server.port))
    sleeper.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    never = ws_client.connect(ws_url(server), sock=sleeper)   # connects, then never reads
    readers = [threading.Thread(target=reader, args=(k,)) for k in range(9)]
    for r in readers:
        r.start()
    try:
        thread.join(timeout=120)
        for r in readers:
            r.join(timeout=30)
    finally:
        stop.set()
        server.close()
        never.close_socket()
    report = out["report"]
    assert report.exit_status == "stopped" and report.ticks == 240
    assert replay(log).identical
    for docs in got:
        seqs = [d["event"]["seq"] for d in docs if d.get("event")]
        assert seqs == sorted(seqs) and docs[-1]["type"] == "stopped" and docs[-1]["event"]["seq"] == 239


def test_controls_are_refused_when_off_and_need_the_token_beyond_loopback(tmp_path):
    server, thread, out, log, feed = live_run(tmp_path, ticks=90)       # controls off
    thread.start()
    try:
        with ws_client.connect(ws_url(server)) as ws:
            ws.send(json.dumps({"action": "stop", "page": "p1"}))
            reply = next(d for d in (json.loads(ws.recv(timeout=10)) for _ in range(500)) if d["type"] == "control")
        assert reply == {"type": "control", "ok": False, "action": "stop",
                         "reason": "controls are off for this run (start it with --view-controls)"}
        thread.join(timeout=120)
    finally:
        server.close()
    assert out["report"].exit_status == "stopped" and out["report"].ticks == 90

    controls = RunControls()
    server = ViewServer.live(LiveFeed(), "0.0.0.0:0", controls)
    try:
        token = server.url.split("?token=")[1]
        assert len(token) >= 16
        with ws_client.connect(ws_url(server)) as ws:
            ws.send(json.dumps({"action": "pause", "page": "p2"}))
            ws.send(json.dumps({"action": "pause", "page": "p2", "token": "guess"}))
            ws.send(json.dumps({"action": "pause", "page": "p2", "token": token}))
            replies = [json.loads(ws.recv(timeout=10)) for _ in range(3)]
    finally:
        server.close()
    assert [r["ok"] for r in replies] == [False, False, True]
    assert replies[0]["reason"] == "wrong or missing token"
    taken = controls.take()
    assert [(r.action, r.by.endswith("page p2")) for r in taken] == [("pause", True)]


def test_the_replay_endpoints_answer_for_the_runs_there_and_refuse_the_others(tmp_path):
    run = ReplayRun(side_push_log(tmp_path / "a.jsonl", ticks=40))
    server = ViewServer.replay([run], "127.0.0.1:0")
    try:
        base = f"http://127.0.0.1:{server.port}/api/"
        assert get_json(base + "frames?run=0&start=10&count=3")["events"] == run.log.events[10:13]
        assert get_json(base + "times?run=0") == run.times
        assert get_json(base + "path?run=0")["robot_m"][0] == run.log.events[0]["obs"]["robot_est_m"]
        for bad in ("frames?run=1", "series?run=x", "times?run=-1", "frames?run=0&start=a"):
            with pytest.raises(urllib.error.HTTPError) as err:
                get_json(base + bad)
            assert err.value.code == 400
    finally:
        server.close()
