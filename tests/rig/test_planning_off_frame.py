"""Planning off the frame: the planned assembly's plan (IPOPT on the pass map, the wavefront path) runs on a worker
thread while the 30 Hz ticks go on, the task holding the robot until the plan is merged (docs/rig.md).

Lock-step runs merge each plan before the next tick, so they are a function of the seed and make the frames of the
on-frame controller (a study's); real-time runs merge it at the first tick that finds it ready. No test here reads
the wall clock: a gated planner returns only after the runtime has ticked on, so the order of events is fixed.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from rig_helpers import FakeClock

from magctl.control.phases import SidePhase
from magctl.control.push.planned import PlannedAssemblyTask
from magctl.control.status import Status
from magctl.rig.log import read_log, replay
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig
from magctl.rig.tasks import Controller, TaskError, build_task

OPTIONS = {"n_spheres": 3}   # `magctl rig run --task assemble --option n_spheres=3 --rig sim --fast`


def deterministic(log) -> tuple:
    """A run log without what the wall clock writes (the timing of each tick, the worker's seconds, uid, dates)."""
    events = [{k: v for k, v in e.items() if k != "timing"} for e in log.events]
    stop = {k: v for k, v in log.stop.items() if k not in ("run", "time_unix")}
    stop["events"] = [{k: v for k, v in ev.items() if k != "worker_s"} for ev in stop.get("events", [])]
    return events, stop


def plans(log) -> list[tuple[int, int]]:
    """(requested, applied) log seq of every plan, from the events' own fields."""
    requested = [e["seq"] for e in log.events if e["outputs"]["event_requested"]]
    applied = {e["outputs"]["event_applied"]: e["seq"] for e in log.events if e["outputs"]["event_applied"] >= 0}
    return [(r, applied.get(r)) for r in requested]


PREFIX_TICKS = 2500


@pytest.mark.slow
def test_lockstep_assembly_plans_off_the_frame_identically_and_converges(tmp_path):
    """Fast runs of the three-sphere assembly on the simulated rig: the plans run on the worker, the runs are
    the same event for event (timing aside), every plan is merged before the tick after the one that asked for
    it, the spheres are assembled, and the on-frame controller (the studies') replays every command bit for bit —
    the frames are those of planning inside the tick."""
    # the whole assembly once; a second run, cut after its first few plans, repeats it event for event
    logs = []
    for k, ticks in enumerate((20000, PREFIX_TICKS)):
        path = tmp_path / f"run{k}.jsonl"
        Runtime(SimRig(n_spheres=3, seed=0), "assemble", OPTIONS, realtime=False, max_ticks=ticks,
                log_path=path, quiet=True).run()
        logs.append(read_log(path))
    assert logs[0].stop["exit_status"] == "done", logs[0].stop.get("reason")
    full, prefix = deterministic(logs[0])[0], deterministic(logs[1])[0]
    assert len(prefix) == PREFIX_TICKS and sum(e["outputs"]["event_requested"] for e in prefix) >= 3
    assert prefix == full[:PREFIX_TICKS]
    log = logs[0]
    made = plans(log)
    assert len(made) >= 10 and all(a == r + 1 for r, a in made)           # plan at frame e, pass from e + 1
    assert [(p["requested"], p["applied"]) for p in log.stop["events"]] == made
    assert not any(e["outputs"]["event_pending"] for e in log.events)     # lock-step: never a tick without it
    assert log.events[-1]["outputs"]["status"] == Status.CONVERGED        # eq 21 on every bond
    assert replay(log.path).identical



class GatedRig(SimRig):
    """A real-time simulated rig that counts its reads and opens a gate once the runtime has read ``n`` more."""

    def __init__(self, **kw):
        super().__init__(n_spheres=3, realtime=True, **kw)
        self.reads = 0
        self.gates: list[tuple[int, threading.Event]] = []
        self.lock = threading.Lock()

    def gate(self, after: int) -> threading.Event:
        ev = threading.Event()
        with self.lock:
            self.gates.append((self.reads + after, ev))
        return ev

    def _read(self):
        with self.lock:
            self.reads += 1
            for n, ev in self.gates:
                if self.reads >= n:
                    ev.set()
        return super()._read()


HOLD = 6
"""Reads the runtime makes while the gated planner waits: the plan is pending for at least this many ticks."""


@pytest.fixture
def gated_planner(monkeypatch):
    """``PlannedAssemblyTask.handle_event`` that, on the worker, waits until the rig has been read ``HOLD`` more
    times before planning; every call is recorded (thread, the rig's reads when it started and returned)."""
    calls, rigs = [], []
    plan = PlannedAssemblyTask.handle_event

    def slow(self, state, u):
        rig = rigs[0] if rigs else None
        on_main = threading.current_thread() is threading.main_thread()
        start = None if rig is None else rig.reads
        if rig is not None and not on_main:
            assert rig.gate(HOLD).wait(60.0), "the runtime stopped ticking while the plan was pending"
        new = plan(self, state, u)
        calls.append({"main": on_main, "start": start, "end": None if rig is None else rig.reads})
        return new

    monkeypatch.setattr(PlannedAssemblyTask, "handle_event", slow)
    return calls, rigs


def test_a_slow_plan_neither_stalls_the_tick_nor_moves_the_robot(tmp_path, monkeypatch, gated_planner):
    """Real time on a fake clock (the ticks run back to back): the planner returns only ``HOLD`` ticks after the
    one that asked for it. That tick returned long before (it did not call the planner: every plan in the loop ran
    on the worker); the plan is merged at a later tick (the log says which); every tick in between sent a command
    with no oscillating field, so the robot stood still — at the first plan and at the second, after a pass (not
    the last pass replayed)."""
    import magctl.rig.runtime as runtime_mod
    import magctl.rig.station as station_mod

    clock = FakeClock()
    monkeypatch.setattr(runtime_mod, "time", clock)
    monkeypatch.setattr(station_mod, "time", clock)
    calls, rigs = gated_planner
    rig = GatedRig()
    rigs.append(rig)
    path = tmp_path / "realtime.jsonl"
    runtime = Runtime(rig, "assemble", OPTIONS, realtime=True, max_ticks=800, log_path=path, quiet=True)
    report = runtime.run()
    assert report.exit_status == "stopped", report.reason
    log = read_log(path)
    made = plans(log)
    assert len(made) >= 2 and all(a is not None for _, a in made[:2])
    loop_calls = [c for c in calls if c["start"] is not None and c["start"] >= 2]  # not the warm-up before the run
    assert len(loop_calls) >= 2 and not any(c["main"] for c in loop_calls)
    for (requested, applied), call in zip(made, loop_calls, strict=False):
        # the requesting tick (its read was the rig's read number requested + 2) had returned long before
        assert call["start"] >= requested + 2 and call["end"] >= requested + 2 + HOLD
        assert applied >= requested + HOLD + 1
        held = log.events[requested + 1:applied]
        assert all(e["outputs"]["event_pending"] for e in held)
        assert all(e["cmd"]["b_osc_T"] == 0.0 and e["cmd"]["freq_Hz"] == 0.0 for e in held)
        robot = np.array([e["obs"]["robot_est_m"] for e in held])
        assert np.ptp(robot, axis=0).max() < 20e-6     # a pixel of tracking noise; travelling moves it 33 µm a frame
        assert log.events[applied]["outputs"]["event_applied"] == requested
    # the second plan follows a pass: the pass before it was not driven again while the plan was pending
    second = made[1][0]
    assert log.events[second]["outputs"]["phase"] == SidePhase.SETTLE    # settled after the pass
    assert [p["requested"] for p in report.events][:2] == [r for r, _ in made[:2]]


@pytest.mark.parametrize("engine", ["compiled", "interpreted"])
def test_a_merged_plan_is_used_from_request_plus_plan_frames_or_when_ready(engine):
    """The controller alone, on one still observation, with ``plan_frames`` = 2. Merged before the next frame, the
    deferred plan gives the frames of the on-frame controller exactly (one held frame, then the repositioning);
    merged two frames late, the frames in between hold the robot and the repositioning starts on the very frame
    of the merge — the wait was counted down meanwhile (never later than needed)."""
    obs = SimRig(n_spheres=3)
    obs.configure()
    first = obs.read()
    task = lambda: build_task("assemble", first, {**OPTIONS, "plan_frames": 2})  # noqa: E731

    def run(defer_at: int | None, frames: int = 8):
        ctrl = Controller(task(), engine=engine, defer_events=defer_at is not None)
        out, waiting = [], []
        for k in range(frames):
            if defer_at is not None and k == defer_at:
                req = waiting.pop()
                ctrl.apply(req, req.run())
            _cmd, outs = ctrl.step(first)
            out.append((float(outs["b_osc"][0]), int(outs["phase"][0]), int(outs["attempt"][0])))
            waiting += ctrl.take_requests()
        return out

    sync = run(None)
    # frame 0 asks for the plan (the robot has no target yet), frame 1 holds for it, frame 2 repositions
    assert [o[0] > 0 for o in sync] == [False, False] + [True] * 6
    assert [o[1] for o in sync[:3]] == [0, 1, 1]
    assert run(1) == sync
    late = run(3)
    assert [o[0] > 0 for o in late] == [False, False, False] + [True] * 5
    assert late[3:] == sync[2:7]


def test_the_controller_refuses_a_result_raised_before_a_reset_and_the_option_is_checked():
    rig = SimRig(n_spheres=3)
    rig.configure()
    first = rig.read()
    ctrl = Controller(build_task("assemble", first, OPTIONS), defer_events=True)
    ctrl.step(first)
    (req,) = ctrl.take_requests()
    assert ctrl.pending == [req] and req.tick == 0
    result = req.run()
    ctrl.reset()
    with pytest.raises(TaskError, match="not pending"):
        ctrl.apply(req, result)
    with pytest.raises(TaskError, match="plan_frames"):
        build_task("assemble", first, {**OPTIONS, "plan_frames": 0})
    two = SimRig(n_spheres=2)
    two.configure()
    with pytest.raises(TaskError, match="plan_frames applies to the planned assembly"):
        build_task("assemble", two.read(), {"plan_frames": 2})
    task = build_task("assemble", first, {**OPTIONS, "plan_frames": 3})
    assert task.options["plan_frames"] == 3 and task.diagram.blocks["task"].plan_frames == 3


def test_a_lockstep_run_with_a_planning_budget_holds_then_replays(tmp_path):
    """``plan_frames=3`` on the rig in lock-step: each plan is merged at the next tick, the task holds the robot
    for the two frames after the request, and the logged options rebuild the controller that replays the run."""
    path = tmp_path / "budget.jsonl"
    report = Runtime(SimRig(n_spheres=3, seed=1), "assemble", {**OPTIONS, "plan_frames": 3}, realtime=False,
                     max_ticks=60, log_path=path, quiet=True).run()
    assert report.exit_status == "stopped" and report.task_options["plan_frames"] == 3
    log = read_log(path)
    assert plans(log) == [(0, 1)]
    # frame 0 asks (the robot has no target yet), frames 1 and 2 hold, frame 3 repositions
    assert [e["cmd"]["b_osc_T"] > 0 for e in log.events[:4]] == [False, False, False, True]
    assert replay(path).identical


def test_a_lockstep_server_is_simulated_time_for_the_plans(start_server, tmp_path):
    """Against a ``--lockstep`` server the runtime paces its ticks (as ``magctl rig run`` does) but the frames follow
    the reads: the plan is merged at the next tick, and the run is the in-process fast run, event for event."""
    from magctl.rig.client import RigClient

    srv = start_server("--lockstep", "--spheres", "3")
    wire, local = tmp_path / "wire.jsonl", tmp_path / "local.jsonl"
    rig = RigClient(srv.address, reset=True)
    try:
        Runtime(rig, "assemble", OPTIONS, realtime=True, max_ticks=45, log_path=wire, quiet=True).run()
    finally:
        rig.close()
    Runtime(SimRig(n_spheres=3), "assemble", OPTIONS, realtime=False, max_ticks=45, log_path=local, quiet=True).run()
    a, b = read_log(wire), read_log(local)
    assert plans(a) == [(0, 1)]
    frames = [[(e["obs"], e["cmd"], e["outputs"]) for e in log.events] for log in (a, b)]
    assert frames[0] == frames[1]
