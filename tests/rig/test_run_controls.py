"""Stop, pause and resume from outside the loop (the live view's buttons), and the monitor the view reads.

In-process ``SimRig(realtime=False)`` runs: one plant frame per tick, so the tick a request is taken at is exact
and the runs are functions of their seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from magctl.rig.log import read_log, replay
from magctl.rig.monitor import RunControls
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig


class Scripted:
    """A monitor that sends control requests when given frames arrive, and keeps what it was given."""

    def __init__(self, controls: RunControls, script: dict[int, str]):
        self.controls, self.script = controls, script
        self.start = self.descriptor = self.stop = None
        self.frames: list[dict] = []
        self.statuses: list[dict] = []

    def run_started(self, start, descriptor):
        self.start, self.descriptor = start, descriptor

    def run_frame(self, event, status):
        self.frames.append(event)
        self.statuses.append(status)
        if event["seq"] in self.script:
            self.controls.request(self.script[event["seq"]], "test page", event["seq"])

    def run_stopped(self, stop):
        self.stop = stop


def run_with(script: dict[int, str], tmp_path, max_ticks=400, monitor_cls=Scripted):
    controls = RunControls()
    monitor = monitor_cls(controls, script)
    log = tmp_path / "run.jsonl"
    report = Runtime(SimRig(n_spheres=1), "side-push", {}, log_path=log, realtime=False, max_ticks=max_ticks,
                     quiet=True, monitor=monitor, controls=controls).run()
    return report, monitor, read_log(log)


def test_pause_holds_the_robot_and_resume_goes_on_and_the_log_still_replays_bit_for_bit(tmp_path):
    report, monitor, log = run_with({99: "pause", 159: "resume"}, tmp_path)
    assert report.exit_status == "stopped" and report.ticks == 400
    ev = log.events
    paused = [e["seq"] for e in ev if e.get("paused")]
    assert paused == list(range(100, 160))     # taken before tick 100's read, released before tick 160's
    assert ev[100]["control"] == [{"action": "pause", "by": "test page"}]
    assert ev[160]["control"] == [{"action": "resume", "by": "test page"}] and not ev[160].get("paused")
    for e in ev[100:160]:
        # the servo's hold: no controller step, no oscillating field, the static field kept (the heading)
        assert e["cmd_raw"] is None and e["cmd"]["b_osc_T"] == 0.0
        assert e["cmd"]["b_static_T"] == ev[99]["cmd"]["b_static_T"]
    moving = np.linalg.norm(np.subtract(ev[99]["obs"]["robot_est_m"], ev[40]["obs"]["robot_est_m"]))
    held = np.linalg.norm(np.subtract(ev[159]["obs"]["robot_est_m"], ev[105]["obs"]["robot_est_m"]))
    # 59 frames of walking cover ~0.8 mm at 0.4-1 mm/s; held, the robot stays within the tracker's noise
    assert moving > 300e-6 and held < 10e-6
    assert ev[170]["cmd"]["b_osc_T"] > 0            # walking again
    assert [s["paused"] for s in monitor.statuses[99:101]] == [False, True]
    assert {s["watchdog_trips"] for s in monitor.statuses} == {0} and monitor.statuses[-1]["ticks"] == 400
    result = replay(log.path)
    assert result.identical and result.compared == 2 * (400 - 60)


def test_stop_ends_the_run_before_the_next_read_with_the_sender_in_the_stop_document(tmp_path):
    report, monitor, log = run_with({120: "stop"}, tmp_path)
    assert report.exit_status == "stopped" and report.ticks == 121
    assert report.reason == "stop button (by test page)"
    assert log.events[-1]["seq"] == 120          # no tick after the one that saw the request
    control = log.stop["control"]
    assert control["action"] == "stop" and control["before_seq"] == 121 and control["seen_seq"] == 120
    assert monitor.stop["exit_status"] == "stopped" and monitor.stop["control"] == control
    assert len(monitor.frames) == 121 and monitor.frames[-1] is not None


def test_a_monitor_that_fails_is_detached_and_the_run_goes_on(tmp_path, capsys):
    class Failing(Scripted):
        def run_frame(self, event, status):
            if event["seq"] == 10:
                raise RuntimeError("browser gone")
            super().run_frame(event, status)

    controls = RunControls()
    monitor = Failing(controls, {})
    report = Runtime(SimRig(n_spheres=1), "side-push", {}, realtime=False, max_ticks=50, monitor=monitor,
                     controls=controls).run()
    assert report.exit_status == "stopped" and report.ticks == 50
    assert len(monitor.frames) == 10
    assert "the live view failed and is detached; the run goes on (RuntimeError: browser gone)" in \
        capsys.readouterr().err


def test_unknown_actions_are_refused_where_they_are_made():
    with pytest.raises(ValueError, match="unknown run control 'launch'"):
        RunControls().request("launch", "me")
    assert RunControls().take() == []
