"""The 30 Hz runtime: tasks converge, overruns are skipped not replayed, loss stops the robot, signals stop safely."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np
import pytest
from rig_helpers import ROOT, FakeClock, magctl_cmd

from magctl.config import load_model
from magctl.control.servo import servo_params
from magctl.core.errors import WiringError
from magctl.rig.client import RigClient
from magctl.rig.log import read_log, replay
from magctl.rig.plant import Scene, build_sim_plant
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig
from magctl.rig.tasks import TaskError

PARAMS = load_model("rig")
SERVO = servo_params()  # the one servo default every controller uses
PERIOD = 1.0 / PARAMS.runtime.rate
EPS_P = 75e-6  # paper §VI-A
SCENE = Scene.default(1)  # robot 1 mm behind the sphere, inside the camera field
START = SCENE.robot
FRONT_GOAL = SCENE.spheres[0] + (750e-6, 0.0)  # paper §VI: 750 µm beyond the sphere, along the push line


def um(xy) -> list[float]:
    return (np.asarray(xy) * 1e6).tolist()


def test_goto_reaches_its_target_on_the_sim_rig():
    rig = SimRig(n_spheres=0)
    target = START + (800e-6, -600e-6)
    report = Runtime(rig, "goto", {"target_um": um(target)}, realtime=False, max_ticks=600, quiet=True).run()
    assert report.exit_status == "done"
    robot = np.array(report.final["robot_um"]) * 1e-6
    assert np.hypot(*(robot - target)) < SERVO.arrive_tol
    # 1 mm at no more than the speed limit takes at least 1 mm / v_max
    assert report.ticks * PERIOD >= 1e-3 / SERVO.speed_max
    assert rig.state.value == "inactive"


def test_front_push_completes_through_the_server_exactly_as_in_process(start_server, tmp_path):
    """The lock-step server steps one frame per read, as ``SimRig(realtime=False)``: the run over the
    wire converges and is the in-process run bit for bit (observations and commands), and replays."""
    srv = start_server("--lockstep")
    wire_log, local_log = tmp_path / "wire.jsonl", tmp_path / "local.jsonl"
    # the paper's model-based feed-forward δ(0) ≈ D_p,r (§V-A) keeps the run short (1-3 attempts, Fig 14: ≤ 4)
    options = {"delta0_um": 300.0}
    rig = RigClient(srv.address, reset=True)
    report = Runtime(rig, "front-push", options, log_path=wire_log, realtime=False, max_ticks=3000,
                     quiet=True).run()
    rig.close()
    assert report.exit_status == "done", (report.reason, report.ticks, report.final)
    # the paper's setting: goal 750 µm beyond the sphere that starts 1 mm ahead of the robot, ε_p = 75 µm
    sphere = np.array(report.final["spheres_um"][0]) * 1e-6
    assert np.hypot(*(sphere - FRONT_GOAL)) < EPS_P
    assert replay(wire_log).identical
    local = Runtime(SimRig(n_spheres=1), "front-push", options, log_path=local_log, realtime=False,
                    max_ticks=3000, quiet=True).run()
    assert local.exit_status == "done" and local.ticks == report.ticks
    wire, here = read_log(wire_log).events, read_log(local_log).events
    assert [(e["obs"], e["cmd_raw"], e["cmd"], e["outputs"]) for e in wire] == \
        [(e["obs"], e["cmd_raw"], e["cmd"], e["outputs"]) for e in here]



class SlowRig(SimRig):
    """A real-time SimRig whose read stalls once (in fake time), long enough to miss ticks."""

    def __init__(self, clock, stall_ticks, stall: float):
        super().__init__(n_spheres=0, realtime=True)
        self.clock, self.reads, self.stall_ticks, self.stall = clock, 0, set(stall_ticks), stall

    def _read(self):
        self.reads += 1
        if self.reads - 2 in self.stall_ticks:  # -1 for the runtime's first read, -1 for 1-based counting
            self.clock.sleep(self.stall)
        return super()._read()


def test_overruns_skip_ticks_count_them_and_never_replay(tmp_path, capsys, monkeypatch):
    """Deterministic: the runtime and the rig run on a fake clock, the stall is 1.6 frames of it."""
    import magctl.rig.runtime as runtime_mod
    import magctl.rig.station as station_mod

    clock = FakeClock()
    monkeypatch.setattr(runtime_mod, "time", clock)
    monkeypatch.setattr(station_mod, "time", clock)
    log = tmp_path / "slow.jsonl"
    # 1.6 frames: long enough to miss tick 6, short enough for the 100 ms watchdog
    rig = SlowRig(clock, stall_ticks=[5, 10], stall=1.6 * PERIOD)
    report = Runtime(rig, "goto", {"target_um": um(START + (1e-3, 0.0))}, log_path=log, realtime=True,
                     max_ticks=20).run()
    events = read_log(log).events
    sched = np.array([e["timing"]["scheduled_s"] for e in events])
    k = np.rint(sched / PERIOD).astype(int)
    # ticks stay on the grid t0 + k T; tick 5 ends after 6 T, so tick 6 is skipped, not run late
    np.testing.assert_allclose(sched, k * PERIOD, atol=1e-9)
    assert report.exit_status == "stopped" and report.overruns == 2
    assert k[5] == 5 and k[6] == 7 and events[6]["timing"]["skipped"] == 1
    assert k[10] == 11 and k[11] == 13 and events[11]["timing"]["skipped"] == 1
    assert len(events) == 20 and np.sum(np.diff(k) - 1) == report.overruns
    # two overruns 0.2 s apart: one warning (at most one a second)
    assert capsys.readouterr().err.count("overrun") == 1


def test_tracking_loss_stops_the_robot_and_ends_the_run(tmp_path):
    scene = Scene.default(0, blackout=(0.5, 100.0))
    rig = SimRig(lambda: build_sim_plant(0, scene), realtime=False)
    log = tmp_path / "lost.jsonl"
    report = Runtime(rig, "goto", {"target_um": um(START + (2e-3, 0.0))}, log_path=log, realtime=False,
                     max_ticks=300, quiet=True).run()
    assert report.exit_status == "tracking-lost"
    events = read_log(log).events
    lost = [e for e in events if e["obs"]["lost"]]
    assert lost and all(e["cmd"]["b_osc_T"] == 0.0 and e["cmd"]["freq_Hz"] == 0.0 for e in lost)
    moving = [e for e in events if not e["obs"]["lost"]]
    assert any(e["cmd"]["b_osc_T"] > 0 for e in moving)
    # stopped after lost_timeout of continuous loss, not earlier
    assert lost[-1]["obs"]["t_s"] - lost[0]["obs"]["t_s"] == pytest.approx(PARAMS.runtime.lost_timeout, abs=PERIOD)
    assert lost[-1]["outputs"]["status"] == 3.0


def test_unknown_task_is_a_clear_error():
    """Refused before the rig is configured: nothing is touched."""
    rig = SimRig(n_spheres=0)
    with pytest.raises(TaskError, match="available: .*goto"):
        Runtime(rig, "juggle", {}, realtime=False, quiet=True).run()
    assert rig.state.value == "unconfigured"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signals_stop_the_run_safely_and_the_server_sees_the_coils_zeroed(start_server, tmp_path, sig):
    # lock-step: the server's watchdog counts frames, so a loaded machine cannot trip it on this healthy client
    srv = start_server("--lockstep", "--plant", "standin")
    log = tmp_path / "term.jsonl"
    proc = subprocess.Popen(magctl_cmd("rig", "run", "--rig", srv.address, "--reset", "--task", "goto",
                                       "--target-um", *map(str, um(START + (3e-3, 0.0))), "--log", str(log),
                                       "--json", "--quiet"),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300        # a cold start compiles the controller first
    while time.monotonic() < deadline and (not log.exists() or log.read_text().count('"event"') < 10):
        time.sleep(0.05)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=10)
    doc = json.loads(out)
    assert doc["exit_status"] == "aborted" and sig.name in doc["reason"]
    run = read_log(log)
    assert run.stop["exit_status"] == "aborted" and run.stop["n_events"] == len(run.events)
    st = RigClient(srv.address).call("status")
    assert st["state"] == "inactive" and st["coils_zero"] and st["watchdog_trips"] == 0


@pytest.mark.parametrize("task, n_spheres, options, words, state", [
    ("assemble", 1, {}, "needs at least 2 tracked sphere", "inactive"),
    ("front-push", 0, {}, "needs at least 1 tracked sphere", "inactive"),
    ("front-push", 1, {"goal_um": [1.0, "x"]}, "goal_um must be two finite numbers", "unconfigured"),
    ("goto", 0, {"speed_max_um_s": -5}, "speed_max_um_s must be positive", "unconfigured"),
    ("side-push", 1, {"model": "quadratic"}, "side-push", "unconfigured"),
    ("goto", 0, {"target_um": [1e9, 1e9]}, "outside the camera's field of view", "unconfigured"),
])
def test_bad_task_options_are_named(task, n_spheres, options, words, state):
    """A bad option is refused before the rig is configured (nothing touched); what needs the first observation
    (the tracked spheres) after activation, with the rig deactivated again."""
    rig = SimRig(n_spheres=n_spheres)
    with pytest.raises(TaskError, match=words):
        Runtime(rig, task, options, realtime=False, quiet=True).run()
    assert rig.state.value == state


def test_front_push_needs_the_learning_law_on_the_sim_rig():
    """Paper §VI-A: K_c = 1 converges on the simulated rig; a naive push that fails is left short of the goal.

    Six plant seeds. On the one plant the in-task release is about 135 µm (the robot turns round to back away,
    release study), so the naive push (K_c = 0, δ(0) = 0) lands within ε_p in some seeds; where it fails it is
    outside ε_p after its 10 attempts. The learning law must converge in at least five of six."""
    naive_failed = learning_done = 0
    for seed in range(6):
        naive = Runtime(SimRig(n_spheres=1, seed=seed), "front-push", {"kc": 0.0}, realtime=False, max_ticks=4000,
                        quiet=True).run()
        learning = Runtime(SimRig(n_spheres=1, seed=seed), "front-push", {"kc": 1.0}, realtime=False,
                           max_ticks=4000, quiet=True).run()
        if naive.exit_status == "failed":
            naive_failed += 1
            assert naive.final["outputs"]["attempt"] == 10
            # outside ε_p after 10 attempts, within a release of the goal: the release's shortfall and the
            # cross-track scatter of the pushes (the robot's turn to back away kicks the sphere sideways)
            error = FRONT_GOAL - np.array(naive.final["spheres_um"][0]) * 1e-6
            assert abs(error[0]) < 500e-6 and np.hypot(*error) > EPS_P
        if learning.exit_status == "done":
            learning_done += 1
            assert 1 <= learning.final["outputs"]["attempt"] < 10
            assert np.hypot(*(np.array(learning.final["spheres_um"][0]) * 1e-6 - FRONT_GOAL)) < EPS_P
    assert naive_failed >= 1 and learning_done >= 5, (naive_failed, learning_done)


def test_side_push_converges_on_the_sim_rig():
    """Paper §VI-B: the model-based learning controller converges within the 30 attempts (ε_p = 7.5 µm)."""
    rig = SimRig(n_spheres=1)
    report = Runtime(rig, "side-push", {}, realtime=False, max_ticks=20000, quiet=True).run()
    assert report.exit_status == "done" and report.final["outputs"]["attempt"] <= 30
    goal = np.array(report.task_options["goal_m"])
    assert np.hypot(*(np.array(report.final["spheres_um"][0]) * 1e-6 - goal)) < 7.5e-6


def test_the_scene_must_start_in_the_camera_field():
    """Camera of models/camera.toml: 640 × 480 pixels of 7.5 µm, field [0, 4792.5] × [0, 3592.5] µm."""
    scene = Scene(robot=np.array([1e-3, 1.8e-3]), spheres=np.array([[4.9e-3, 1.8e-3]]))
    with pytest.raises(WiringError, match=r"outside the camera's field of view \[0, 4792\] × \[0, 3592\] µm"):
        build_sim_plant(1, scene)
    build_sim_plant(1, scene, plant="standin")  # the stand-in tracker sees a 10 mm square around the origin
    with pytest.raises(WiringError, match="plant 'kinematic' is not one of physics, standin"):
        build_sim_plant(1, plant="kinematic")


def test_the_physical_plant_starts_tracked_where_the_scene_puts_it():
    """Camera and tracker are primed with the scene: frame 0 reports it (to the 7.5 µm pixel), not lost."""
    plant = build_sim_plant(2)
    state = plant.initial_state(1, seed=0)
    u = {"b_static": np.zeros((1, 2)), "b_osc": np.zeros(1), "freq": np.zeros(1)}
    out = plant.output(state, u)
    scene = Scene.default(2)
    pixel = load_model("camera").camera.pixel_size
    assert not out["lost"][0]
    np.testing.assert_allclose(out["robot_est"][0], scene.robot, atol=pixel)
    np.testing.assert_allclose(out["spheres_est"][0], scene.spheres, atol=pixel)


def test_three_sphere_assembly_through_the_command_line_against_the_server(start_server, tmp_path):
    """`magctl rig run --task assemble --option n_spheres=3` against `serve-sim` on loopback (its own process,
    lock-step): the planned assembly plans, repositions and starts its first pass, logs every frame and leaves
    the coils at zero."""
    srv = start_server("--lockstep", "--spheres", "3", "--sphere-um", "2000", "1800", "--sphere-um", "2420", "1780",
                       "--sphere-um", "2190", "2160")
    log = tmp_path / "assemble.jsonl"
    proc = subprocess.run(magctl_cmd("rig", "run", "--rig", srv.address, "--task", "assemble", "--option",
                                     "n_spheres=3", "--option", "arrangement=triangle", "--max-ticks", "250",
                                     "--log", str(log), "--json", "--quiet"),
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["exit_status"] == "stopped" and doc["ticks"] == 250
    run = read_log(log)
    assert run.start["task"] == "assemble" and run.start["options"]["n_spheres"] == 3
    assert len(run.events) == 250
    phases = [e["outputs"]["phase"] for e in run.events]
    assert 1 in phases and 2 in phases   # repositioned along the wavefront path, then on the pass
    st = RigClient(srv.address).call("status")
    assert st["state"] == "inactive" and st["coils_zero"]


@pytest.mark.parametrize("origin_um", [None, (300.0, 300.0), (4500.0, 300.0), (300.0, 3300.0), (4500.0, 3300.0)])
def test_a_patrol_square_turns_towards_the_middle_of_the_field(origin_um, tmp_path):
    """From the simulated rig's own start (``None``) and from near each corner of the 4.8 × 3.6 mm field, the
    default 1 mm square lies in the field: the robot is driven round it, first along y, then along x."""
    from magctl.sensing.camera import field_of_view

    options = {} if origin_um is None else {"origin_um": list(origin_um)}
    log = tmp_path / "patrol.jsonl"
    report = Runtime(SimRig(n_spheres=0), "patrol", options, log_path=log, realtime=False, max_ticks=5,
                     quiet=True).run()
    assert report.exit_status == "stopped", report.reason
    start = read_log(log).start
    origin = np.array(start["options"].get("origin_m") or np.array(origin_um) * 1e-6)
    w, h = field_of_view()
    corners = origin + 1e-3 * np.array([[0, 1], [1, 1], [1, 0]]) * np.sign(np.array([w, h]) / 2 - origin)
    assert np.all((corners >= 0) & (corners <= (w, h)))
