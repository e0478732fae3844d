"""The live and replay pages in a real headless Chromium (Debian's ``chromium``, driven by playwright).

The live run is a ``magctl rig run --view`` process against a ``serve-sim --lockstep`` server (one plant frame per
read: the frames are a function of the seed, whatever the browser does); the replay page is ``magctl log view``
over logs written in this process. What the page drew is checked against the log twice over: the page's own record
of where it drew each object (``window.magctlView.drawn``) and the canvas pixels at the place the log's position
maps to, with the drawing scale recomputed here from the camera field.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import signal
import sys
import time

import numpy as np
import pytest
import zmq
from PIL import Image
from view_helpers import CHROMIUM_ARGS, ROOT, MagctlProcess, chromium_path, free_port

from magctl.rig import protocol as P
from magctl.rig.log import read_log
from magctl.rig.runtime import Runtime
from magctl.rig.server import start_server
from magctl.rig.sim import SimRig
from magctl.sensing.camera import field_of_view

CANVAS = (560, round(560 * 0.78))
MARGIN = 10
ROBOT_RGB, SPHERE_RGB = (0xD9, 0x48, 0x0F), (0x19, 0x71, 0xC2)
SCREENSHOTS = os.environ.get("MAGCTL_VIEW_SCREENSHOTS")
"""A folder to copy the tests' screenshots into (docs/figures for the docs' pictures); unset: tmp only."""


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="the dev extra installs playwright")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser):
    pg = browser.new_page(viewport={"width": 1500, "height": 1150}, accept_downloads=True)
    pg.errors = []
    pg.on("console", lambda m: pg.errors.append(m.text) if m.type == "error" else None)
    pg.on("pageerror", lambda e: pg.errors.append(str(e)))
    yield pg
    pg.close()


def expected_px(xy) -> tuple[float, float]:
    """Where the page must draw a point of the camera field (y up, 10 px margin, the field fitted)."""
    w, h = field_of_view()
    scale = min((CANVAS[0] - 2 * MARGIN) / w, (CANVAS[1] - 2 * MARGIN) / h)
    return MARGIN + xy[0] * scale, CANVAS[1] - MARGIN - xy[1] * scale


SNAPSHOT_JS = """([k, pts]) => {
  const v = window.magctlView, d = v.drawn[k], ctx = v.runs[k].canvas.getContext('2d');
  const rgb = pts.map(p => Array.from(ctx.getImageData(Math.round(p[0]), Math.round(p[1]), 1, 1).data.slice(0, 3)));
  return {drawn: JSON.parse(JSON.stringify(d)), rgb: rgb};
}"""


def check_drawn_against_log(page, events_by_seq, k=0):
    """The page's last drawn frame of run ``k`` against the log: positions within 1 px, the canvas coloured
    there."""
    d = page.evaluate("(k) => JSON.parse(JSON.stringify(window.magctlView.drawn[k]))", k)
    ev = events_by_seq[d["seq"]]
    robot = expected_px(ev["obs"]["robot_est_m"])
    spheres = [expected_px(s) for s in ev["obs"]["spheres_est_m"]]
    snap = page.evaluate(SNAPSHOT_JS, [k, [robot, *spheres]])
    if snap["drawn"]["seq"] != d["seq"]:      # a new frame came between the two reads: take the newer one
        return check_drawn_against_log(page, events_by_seq, k)
    assert math.dist(snap["drawn"]["robot_px"], robot) <= 1.0
    for drawn, want in zip(snap["drawn"]["spheres_px"], spheres, strict=True):
        assert math.dist(drawn, want) <= 1.0
    assert np.abs(np.subtract(snap["rgb"][0], ROBOT_RGB)).max() <= 2
    for rgb in snap["rgb"][1:]:
        assert np.abs(np.subtract(rgb, SPHERE_RGB)).max() <= 2
    return d["seq"]


def server_status(address: str) -> dict:
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 5000)
    sock.connect(address)
    try:
        sock.send(json.dumps(P.request("status", 1)).encode())
        return json.loads(sock.recv())
    finally:
        sock.close(0)


def save_screenshot(page, tmp_path, name):
    path = tmp_path / name
    page.screenshot(path=str(path), full_page=True)
    assert Image.open(path).format == "PNG"
    if SCREENSHOTS:
        shutil.copy(path, os.path.join(SCREENSHOTS, name))


def test_the_live_page_draws_the_run_where_the_log_says_and_its_stop_button_zeroes_the_coils(page, tmp_path):
    address = f"tcp://127.0.0.1:{free_port()}"
    server = start_server([sys.executable, "-m", "magctl", "rig", "serve-sim", "--lockstep", "--bind", address],
                          cwd=ROOT)
    run = None
    try:
        log = tmp_path / "live.jsonl"
        run = MagctlProcess("rig", "run", "--rig", address, "--task", "side-push", "--view", "127.0.0.1:0",
                            "--view-controls", "--log", str(log), "--duration", "300")
        page.goto(run.url())
        page.wait_for_function("window.magctlView.drawn.length > 0 && window.magctlView.drawn[0].seq >= 30",
                               timeout=300_000)
        first = page.evaluate("window.magctlView.drawn[0].seq")
        page.wait_for_function(f"window.magctlView.drawn[0].seq >= {first + 20}", timeout=60_000)
        page.wait_for_timeout(300)
        save_screenshot(page, tmp_path, "view-live.png")
        page_id = page.evaluate("window.magctlView.pageId")
        page.click("#stop")
        assert run.wait(timeout=60) == 0, run.lines
        page.wait_for_function("window.magctlView.ended === true", timeout=30_000)
        message = page.text_content("#message")
        status = server_status(address)
    finally:
        if run is not None:
            run.kill()
        server.kill()
        server.wait(timeout=10)
    rl = read_log(log)
    by_seq = {e["seq"]: e for e in rl.events}
    # what the page drew, after the run: its last frame, against the log
    check_drawn_against_log(page, by_seq)
    assert rl.stop["exit_status"] == "stopped"
    assert rl.stop["reason"].startswith("stop button (by 127.0.0.1:") and f"page {page_id}" in rl.stop["reason"]
    control = rl.stop["control"]
    # the stop is taken before the read of the tick after the newest frame the page had been sent, or of the one
    # after that if a tick was under way: at most one more frame was commanded
    assert rl.events[-1]["seq"] == control["before_seq"] - 1
    assert 0 <= control["before_seq"] - (control["seen_seq"] + 1) <= 1
    assert status["coils_zero"] and status["state"] != "active"
    assert "run ended: stopped — stop button" in message
    assert page.errors == []


def wait_for_draw(page, run, condition: str, timeout_s: float):
    """Wait until ``condition`` holds on the page; a run that ended first fails at once with what it printed."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            page.wait_for_function(condition, timeout=2_000)
            return
        except PlaywrightTimeout:
            if run.proc.poll() is not None:
                raise AssertionError(f"the run ended (exit {run.wait()}) before {condition!r}: "
                                     f"{run.lines} {run.stdout}") from None
            if time.monotonic() > deadline:
                raise


def test_the_live_page_follows_the_frames_and_a_signal_ends_the_run_in_order(page, tmp_path):
    """Two draws apart, both where the log says; SIGTERM (as Ctrl-C) aborts the run after a whole tick with the
    coils at zero, the page says so. Against a lock-step server: on a loaded machine the in-process rig's 100 ms
    watchdog may rightly end a real-time run; the server's watchdog counts simulated frames."""
    address = f"tcp://127.0.0.1:{free_port()}"
    server = start_server([sys.executable, "-m", "magctl", "rig", "serve-sim", "--lockstep", "--bind", address],
                          cwd=ROOT)
    log = tmp_path / "follow.jsonl"
    run = MagctlProcess("rig", "run", "--rig", address, "--task", "side-push", "--view", "127.0.0.1:0", "--log",
                        str(log), "--duration", "300")
    try:
        page.goto(run.url())
        wait_for_draw(page, run, "window.magctlView.drawn.length > 0 && window.magctlView.drawn[0].seq >= 20", 300)
        seqs = [page.evaluate("window.magctlView.drawn[0].seq")]
        wait_for_draw(page, run, f"window.magctlView.drawn[0].seq >= {seqs[0] + 30}", 60)
        seqs.append(page.evaluate("window.magctlView.drawn[0].seq"))
        assert page.evaluate("document.getElementById('stop').disabled")       # controls off without the flag
        run.proc.send_signal(signal.SIGTERM)
        assert run.wait(timeout=60) == 1, (run.lines, run.stdout)      # a signal is an abort: not a task's end
        page.wait_for_function("window.magctlView.ended === true", timeout=30_000)
        message = page.text_content("#message")
        status = server_status(address)
    finally:
        run.kill()
        server.kill()
        server.wait(timeout=10)
    assert seqs[1] >= seqs[0] + 30
    rl = read_log(log)
    assert rl.stop["exit_status"] == "aborted" and rl.stop["reason"] == "signal SIGTERM"
    assert status["coils_zero"] and status["state"] != "active"
    assert "run ended: aborted — signal SIGTERM" in message
    by_seq = {e["seq"]: e for e in rl.events}
    check_drawn_against_log(page, by_seq)
    assert page.errors == []


def side_push_log(path, seed):
    Runtime(SimRig(n_spheres=1, seed=seed), "side-push", {}, log_path=path, realtime=False, seed=seed,
            max_ticks=3000, quiet=True).run()
    return read_log(path)


def attempt_end(events, goal, attempt):
    """The frame where the task's attempt counter reaches ``attempt``, and the nearest sphere's distance to the
    goal there."""
    prev = None
    for e in events:
        a = e["outputs"]["attempt"]
        if prev is not None and prev < attempt <= a:
            return e["seq"], min(math.dist(s, goal) for s in e["obs"]["spheres_est_m"])
        prev = a
    raise AssertionError(f"no attempt {attempt} in the log")


def test_the_replay_page_scrubs_jumps_to_attempts_plays_and_exports(page, tmp_path):
    logs = [side_push_log(tmp_path / f"run{seed}.jsonl", seed) for seed in (0, 1)]
    view = MagctlProcess("log", "view", *(str(lg.path) for lg in logs), "--view", "127.0.0.1:0", "--duration", "300")
    try:
        page.goto(view.url())
        page.wait_for_function("window.magctlView.ready === true", timeout=60_000)
        assert page.locator("canvas").count() == 2                      # side by side
        by_seq = [{e["seq"]: e for e in lg.events} for lg in logs]
        goal = logs[0].start["options"]["goal_m"]

        # jump to the end of the first run's attempt 2: its frame and its error, as the log has them
        seq, error = attempt_end(logs[0].events, goal, 2)
        page.click('#attempt-jumps button[data-run="0"][data-attempt="2"]')
        page.wait_for_function("window.magctlView.shownAttempt && window.magctlView.shownAttempt.attempt === 2")
        shown = page.evaluate("window.magctlView.shownAttempt")
        assert shown["seq"] == seq and shown["error_um"] == pytest.approx(error * 1e6, rel=1e-12)
        assert page.evaluate("window.magctlView.drawn[0].seq") == seq
        assert f"sphere–goal {error * 1e6:.1f} µm at seq {seq}" in page.text_content("#message")
        check_drawn_against_log(page, by_seq[0], 0)

        # scrub to 5.01 s: each run shows its last frame at or before its start + 5.01 s
        page.evaluate("() => { const el = document.getElementById('timeline'); el.value = '5.01';"
                      " el.dispatchEvent(new Event('input')); }")
        for k, lg in enumerate(logs):
            t0 = lg.events[0]["obs"]["t_s"]
            want = max(e["seq"] for e in lg.events if e["obs"]["t_s"] - t0 <= 5.01)
            page.wait_for_function(f"window.magctlView.drawn[{k}].seq === {want}", timeout=10_000)
            check_drawn_against_log(page, by_seq[k], k)

        # play at 16×: the frames advance
        page.select_option("#speed", "16")
        before = page.evaluate("window.magctlView.drawn[0].seq")
        page.click("#play")
        page.wait_for_function(f"window.magctlView.drawn[0].seq > {before + 60}", timeout=30_000)
        page.click("#play")

        # export the scene as drawn
        with page.expect_download() as download:
            page.click("#export")
        png = Image.open(io.BytesIO(open(download.value.path(), "rb").read()))
        assert png.format == "PNG" and png.size == CANVAS
        page.click('#attempt-jumps button[data-run="0"][data-attempt="2"]')
        page.wait_for_timeout(300)
        save_screenshot(page, tmp_path, "view-replay.png")
    finally:
        view.kill()
    assert page.errors == []


def test_with_a_labs_camera_the_page_shows_its_frame_under_the_tracked_outlines(page, tmp_path):
    """``--rig examples/lab-sim.toml`` in process: the camera frames (rendered, PNG-coded, tracked) are drawn on
    the glass through the pixel calibration, so the still sphere's image lies inside its tracked outline. In
    simulated time (``--fast``): a real-time lab run on a loaded machine may rightly end at a missed deadline before
    the page has a frame (docs/rig.md, the lab soak); what is checked here is the picture."""
    log = tmp_path / "lab.jsonl"
    run = MagctlProcess("rig", "run", "--rig", str(ROOT / "examples" / "lab-sim.toml"), "--task", "side-push",
                        "--view", "127.0.0.1:0", "--log", str(log), "--fast", "--duration", "3600")
    try:
        page.goto(run.url())
        # a cold start compiles the tracker and builds the board's firmware before the first frame: wait for it
        wait_for_draw(page, run, "window.magctlView.drawn.length > 0 && window.magctlView.drawn[0].camera >= 2", 300)
        d = page.evaluate("JSON.parse(JSON.stringify(window.magctlView.drawn[0]))")
        sphere = d["spheres_px"][0]
        empty = (sphere[0] + 40, sphere[1] + 40)          # 355 µm from the sphere's centre: the oil
        rgb = page.evaluate(SNAPSHOT_JS, [0, [sphere, empty]])["rgb"]
        run.proc.send_signal(signal.SIGTERM)
        assert run.wait(timeout=120) == 1, (run.lines, run.stdout)       # a signal is an abort
    finally:
        run.kill()
    assert read_log(log).stop["reason"] == "signal SIGTERM"
    centre, oil = np.mean(rgb[0]), np.mean(rgb[1])
    # the sphere renders at 0.4 of the 0.8 background (models/camera.toml [render]): half as bright
    assert centre < 0.75 * oil and oil > 120
    assert page.errors == []
