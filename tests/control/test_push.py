"""Push tasks end to end at 30 Hz on the kinematic stand-in plant, against the iteration-domain maps.

Two compositions of :mod:`magctl.plant.standin`:

* the **ideal loop** — task → ``StraightToTarget`` (the servo the attempt maps assume) →
  ``KinematicRobot`` → ``StandinSpheres`` → ``StandinTracker``: the task must reproduce the
  maps of :mod:`magctl.stability.iteration` trial by trial, from the drawn ``D_p,r``;
* the **rig's loop** — :func:`magctl.loops.controller` (task → PI servo → drive) closed with
  :func:`magctl.loops.closed_loop` round ``magctl.loops.plant(scene, kind="standin")``
  (coils → gait → kinematic robot → spheres → tracker): what ``magctl rig`` runs.
"""

import control
import numpy as np
import pytest

from magctl import FRAME_PERIOD_S as T
from magctl.control.learning import front_push_law, side_push_law
from magctl.control.push.assembly import AssemblyTask, FrontAssemblyTask, FrontThenSideAssemblyTask
from magctl.control.push.front import FrontPushTask
from magctl.control.push.side import SidePushTask
from magctl.control.status import Status
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.loops import Scene, closed_loop, controller, geometry, plant
from magctl.plant.standin import KinematicRobot, StandinSpheres, StandinTracker, StraightToTarget, standin_params
from magctl.stability import iteration as S

CONVERGED, ATTEMPT_LIMIT, TRACKING_LOST = Status.CONVERGED, Status.ATTEMPT_LIMIT, Status.TRACKING_LOST
RUNNING = Status.RUNNING
SPHERE_LOST, STALLED = Status.SPHERE_LOST, Status.STALLED

CONVERGED, ATTEMPT_LIMIT = Status.CONVERGED, Status.ATTEMPT_LIMIT
EXACT = {"arrive_tol": 0.1 * UM}  # the ideal servo lands the robot exactly on its targets


def ideal_loop(task, robot0, spheres0, *, v_max=1e-3, side_range=None, blackout=None, sphere_loss=None,
               release=True, side_scale=1.0):
    """``task`` round the ideal servo and the stand-in robot, spheres and tracker (``release=False``: the
    spheres are not pulled back when the robot leaves them; ``side_scale``: eq 22 scaled, per trial)."""
    p = standin_params()
    spheres0 = np.asarray(spheres0, dtype=float)
    n = task.name
    blocks = [
        task,
        StraightToTarget("servo", v_max=v_max),
        KinematicRobot("robot", start=robot0),
        StandinSpheres("spheres", spheres0, p.contact_distance, release_mean=p.release_mean if release else 0.0,
                       release_std=p.release_std if release else 0.0,
                       side_range=p.side_range if side_range is None else side_range,
                       sphere_radius=p.sphere_radius, start_robot=robot0, side_scale=side_scale),
        StandinTracker("tracker", len(spheres0), p.workspace_half, blackout, robot0, 0.0, spheres0,
                       sphere_loss=sphere_loss),
    ]
    return Diagram("loop", blocks, [
        ("tracker.robot_est", f"{n}.robot_est"), ("tracker.spheres_est", f"{n}.spheres_est"),
        ("tracker.lost", f"{n}.lost"),
        (f"{n}.target", "servo.target"), (f"{n}.speed_cap", "servo.speed_cap"), ("robot.position", "servo.position"),
        ("servo.speed", "robot.speed"), ("servo.heading", "robot.heading"),
        ("robot.position", "spheres.position"), ("robot.position", "tracker.position"),
        ("robot.heading", "tracker.heading"), ("spheres.spheres", "tracker.spheres"),
    ])


def rig_loop(task, *, blackout=None, speed_max=None, **options):
    """The rig's controller for ``task`` in the paper's set-up, round the stand-in plant of ``magctl.loops``."""
    g = geometry({"front-push": "front", "side-push": "side"}[task])
    scene = Scene(robot=g["robot"], spheres=g["spheres"], blackout=blackout)
    ctrl = controller(task, n_spheres=1, goal=g["goal"], speed_max=speed_max, **options)
    return closed_loop(ctrl, plant(scene, kind="standin")), g


def release_starts(count):
    """Frames at which each trial's releases start, (B,) lists."""
    return [np.flatnonzero(np.diff(c) > 0) + 1 for c in count]


def drawn_releases(count, last, n):
    """The ``D_p,r`` each trial drew, attempt by attempt (B, n); 300 µm where no release happened."""
    out = np.full((count.shape[0], n), 300 * UM)
    for b, starts in enumerate(release_starts(count)):
        v = last[b, starts][:n]
        out[b, : len(v)] = v
    return out


@pytest.mark.parametrize("kc,delta0", [(1.0, 0.0), (0.5, 127 * UM)])
def test_front_push_matches_the_attempt_map_trial_by_trial(kc, delta0):
    law = front_push_law(kc, delta0)
    task = FrontPushTask(goal=(750 * UM, 0.0), law=law, push_tol=0.1 * UM, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0]]), 1800, batch=48, seed=7)
    status, att = res["front_push.status"][:, -1], res["front_push.attempt"][:, -1]
    assert set(status) <= {CONVERGED, ATTEMPT_LIMIT}
    assert len(set(att)) > 1  # the draws matter: trials take different numbers of attempts
    pred = S.front_attempt_map(kc, delta0, drawn_releases(res["spheres.releases"], res["spheres.last_release"], 10))
    np.testing.assert_array_equal(np.where(status == CONVERGED, att, -1), pred["attempts"])
    # the same law object is the iteration-domain system
    assert control.poles(S.front_iteration_diagram(task.law).to_control()) == pytest.approx([1 - kc])
    # converged trials end within ε_p of the goal (eq 12)
    s = res["tracker.spheres_est"][status == CONVERGED, -1, 0]
    assert np.all(np.hypot(s[:, 0] - 750 * UM, s[:, 1]) < 75 * UM)


def test_front_push_on_the_rig_loop_matches_the_attempt_map_trial_by_trial():
    """The rig's controller and the stand-in plant: the map, fed each attempt's drawn D_p,r plus the servo's
    shortfall at the end of the push, predicts every trial's attempt count; the shortfall is within the
    servo's arrival tolerance plus a frame of lag (under 2 camera pixels): the map's ideal servo to a pixel or two."""
    kc, delta0 = 0.5, 127 * UM
    dia, g = rig_loop("front-push", kc=kc, delta0=delta0, push_tol=0.1 * UM)
    rec = ["controller/task.status", "controller/task.attempt", "controller/task.correction", "plant/spheres.spheres",
           "plant/spheres.releases", "plant/spheres.last_release"]
    res = simulate(dia, 2400, batch=16, seed=11, record=rec)
    status, att = res[rec[0]][:, -1], res[rec[1]][:, -1]
    assert set(status) <= {CONVERGED, ATTEMPT_LIMIT} and CONVERGED in status
    x_goal = g["goal"][0]  # the push line is the x axis
    sx = res[rec[3]][:, :, 0, 0]
    eff = np.full((status.shape[0], 10), 300 * UM)
    for b, starts in enumerate(release_starts(res[rec[4]])):
        starts = starts[:10]
        begun = np.concatenate([[0], np.flatnonzero(np.diff(res[rec[1]][b]) > 0) + 1])[: len(starts)]
        u = np.sign(x_goal - sx[b, begun])  # the attempt's push direction, P_s → P_g
        p_o = x_goal + res[rec[2]][b, starts - 1] * u  # eq 10: P_o = P_g + δ(i)·u
        shortfall = (p_o - sx[b, starts - 1]) * u  # how far short of P_o the push left the sphere
        assert np.all((shortfall > 0) & (shortfall < 15 * UM))  # the servo stops short, by under 2 pixels
        eff[b, : len(starts)] = res[rec[5]][b, starts] + shortfall
    pred = S.front_attempt_map(kc, delta0, eff)["attempts"]
    np.testing.assert_array_equal(np.where(status == CONVERGED, att, -1), pred)
    s = res[rec[3]][status == CONVERGED, -1, 0]
    assert np.all(np.linalg.norm(s - g["goal"], axis=1) < 75 * UM)


def test_naive_front_push_hits_the_attempt_limit():
    task = FrontPushTask(goal=(750 * UM, 0.0), kc=0.0, delta0=0.0, max_attempts=4, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0]]), 900, batch=8, seed=2)
    assert np.all(res["front_push.status"][:, -1] == ATTEMPT_LIMIT)
    assert np.all(res["front_push.attempt"][:, -1] == 4)
    # no compensation: the sphere stays short of the goal by D_p,r plus what the push left within its eq 11
    # tolerance (ε_p = 75 µm, as printed) — §VI-A's naive steady error
    short = 750 * UM - res["spheres.spheres"][:, -1, 0, 0] - res["spheres.last_release"][:, -1]
    assert np.all((short >= -1e-12) & (short < 75 * UM))
    assert np.all(750 * UM - res["spheres.spheres"][:, -1, 0, 0] > 75 * UM)


@pytest.mark.parametrize("ks,model", [(0.9, "lin"), (0.0, "exp")])
def test_side_push_converges_as_the_map_predicts(ks, model):
    task = SidePushTask(goal=(300 * UM, 0.0), ks=ks, model=model, clearance=850 * UM, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0]]), 2600, batch=1)
    pred = S.side_attempt_map(ks, 300 * UM, model=model)
    assert res["side_push.status"][0, -1] == CONVERGED
    assert res["side_push.attempt"][0, -1] == pred["attempts"][0] <= 10
    s = res["tracker.spheres_est"][0, -1, 0]
    assert np.hypot(s[0] - 300 * UM, s[1]) < 7.5 * UM


def test_side_push_with_the_printed_eq_18_sign_fails_explicitly():
    law = side_push_law(0.9, printed_sign=True)  # eq 18 exactly as printed
    task = SidePushTask(goal=(280 * UM, 0.0), law=law, model="lin", clearance=850 * UM, max_attempts=8, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0]], side_range=600 * UM), 2600, batch=1)
    assert res["side_push.status"][0, -1] == ATTEMPT_LIMIT
    assert res["side_push.attempt"][0, -1] == 8
    # Δ grows every attempt and the gap sits on its lower bound: the over-push is reinforced
    a = res["side_push.attempt"][0]
    ends = np.flatnonzero(np.diff(a) > 0)
    assert np.all(np.diff(res["side_push.correction"][0, ends]) > 0)
    assert np.allclose(res["side_push.gap"][0, ends], task.min_gap)
    assert S.side_attempt_map(0.9, 280 * UM, model="lin", printed_sign=True)["attempts"][0] == -1


def test_side_push_assembly_terminates_by_eq_21():
    task = AssemblyTask(ks=0.9, model="lin", clearance=850 * UM, eps_as=10 * UM, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 300 * UM), [[0.0, 0.0], [500 * UM, 0.0]]), 3000, batch=1)
    assert res["assembly.status"][0, -1] == CONVERGED
    s1, s2 = res["tracker.spheres_est"][0, -1]
    assert np.linalg.norm(s2 - s1) <= 210 * UM + 10 * UM
    assert 1 <= res["assembly.attempt"][0, -1] <= 30


def test_front_push_assembly_fails_as_in_the_paper():
    task = FrontAssemblyTask(kc=1.0, max_attempts=3, eps_as=10 * UM, **EXACT)
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0], [800 * UM, 0.0]]), 1500, batch=4, seed=1)
    assert np.all(res["front_assembly.status"][:, -1] == ATTEMPT_LIMIT)
    s = res["spheres.spheres"][:, -1]
    assert np.all(np.linalg.norm(s[:, 1] - s[:, 0], axis=1) > 220 * UM)
    # the spheres never overlap (the stand-in separates them)
    gaps = np.linalg.norm(res["spheres.spheres"][:, :, 1] - res["spheres.spheres"][:, :, 0], axis=-1)
    assert gaps.min() >= 210 * UM * (1 - 1e-9)


LATE = (40.5 * T, np.inf)  # from frame 41 on


@pytest.mark.parametrize("plant_kw,task_kw,code", [
    ({"blackout": LATE}, {}, Status.TRACKING_LOST),
    ({"sphere_loss": LATE}, {}, Status.SPHERE_LOST),
    ({"v_max": 1e-6}, {"phase_timeout_frames": 60}, Status.STALLED),
])
def test_failure_modes_end_the_task(plant_kw, task_kw, code):
    task = FrontPushTask(goal=(750 * UM, 0.0), **task_kw)
    # a vanished sphere is reported as NaN, which the finiteness check would stop on
    res = simulate(ideal_loop(task, (-1e-3, 0.0), [[0.0, 0.0]], **plant_kw), 200, batch=2, check_finite=False)
    status = res["front_push.status"]
    assert np.all(status[:, -1] == code)
    assert np.all(status[:, 40] == Status.RUNNING)  # nothing went wrong before the injected fault
    assert np.all(res["front_push.speed_cap"][:, -1] == 0)


@pytest.mark.parametrize("kw,code", [({"blackout": LATE}, Status.TRACKING_LOST),
                                     ({"speed_max": 1e-6, "phase_timeout_frames": 60}, Status.STALLED)])
def test_failure_modes_end_the_task_on_the_rig_loop(kw, code):
    dia, _ = rig_loop("front-push", **kw)
    rec = ["controller/task.status", "controller/drive.b_osc", "plant/robot.position"]
    res = simulate(dia, 200, batch=2, seed=0, record=rec)
    assert np.all(res[rec[0]][:, -1] == code)
    assert np.all(res[rec[0]][:, 40] == Status.RUNNING)
    # the servo's hold stops the drive: no rocking field, the robot stands still
    assert np.all(res[rec[1]][:, -5:] == 0)
    np.testing.assert_array_equal(res[rec[2]][:, -1], res[rec[2]][:, -5])


def test_batch_independence_on_the_rig_loop():
    dia, _ = rig_loop("front-push", kc=1.0)
    rec = ["controller/task.target", "plant/spheres.spheres", "plant/spheres.last_release"]
    big = simulate(dia, 900, batch=6, seed=4, record=rec)
    one = simulate(dia, 900, batch=1, seed=4, trials=[3], record=rec)
    for k in rec:
        np.testing.assert_array_equal(big[k][3], one[k][0])
    assert len({float(x) for x in big[rec[2]][:, -1]}) > 1  # trials draw their own D_p,r


def test_task_outputs_not_mutated():
    task = FrontPushTask(goal=(750 * UM, 0.0), kc=1.0, **EXACT)
    st = task.initial_state(2)
    u = {"robot_est": np.zeros((2, 2)), "spheres_est": np.full((2, 1, 2), 1e-4), "lost": np.zeros(2, bool)}
    out = task.output(st, u)
    keep = {k: v.copy() for k, v in out.items()}
    for _ in range(3):
        st = task.update(st, u)
    for k in out:
        np.testing.assert_array_equal(out[k], keep[k])


def test_bad_task_parameters_are_named():
    with pytest.raises(MagctlError, match="sphere index 2"):
        FrontPushTask(goal=(0, 0), sphere=2)
    with pytest.raises(MagctlError, match="goal"):
        SidePushTask(goal=(0, 0, 0))
    with pytest.raises(MagctlError, match="eps"):
        SidePushTask(goal=(0, 0), eps=-1)
    with pytest.raises(MagctlError, match="theta_n"):
        AssemblyTask(theta_n=2.0)
    with pytest.raises(MagctlError, match="must differ"):
        AssemblyTask(moved=1, fixed=1)


def test_a_configuration_without_a_kernel_is_refused():
    """A push task's behaviour is its kernel: a law or side-push model of a kind the kernels do not run is named
    at construction."""
    from magctl.control.curve_learning import curve_learning_law
    from magctl.control.learning import LearningLaw
    from magctl.stability.switched import ScaledSideModel

    class OwnLaw(LearningLaw):
        pass

    with pytest.raises(MagctlError, match="front push 'front_push': its kernels run no law of type "
                                          "CurveLearningLaw; give a LearningLaw or a ReleasePolicyLaw"):
        FrontPushTask(goal=(0, 0), law=curve_learning_law())
    with pytest.raises(MagctlError, match="side push 'side_push': its kernels run no law of type OwnLaw"):
        SidePushTask(goal=(0, 0), law=OwnLaw("own", -0.9))
    with pytest.raises(MagctlError, match="assembly_side'.*no law of type OwnLaw"):
        FrontThenSideAssemblyTask(law=OwnLaw("own", -0.9))
    with pytest.raises(MagctlError, match="no model of type ScaledSideModel; give one of lin, exp"):
        SidePushTask(goal=(0, 0), model=ScaledSideModel(scale=2.0))
    assert FrontPushTask(goal=(0, 0), law=front_push_law([0.5, 1.0])).kernel() is not None   # per-trial K_c


@pytest.mark.slow
def test_front_push_runs_on_the_plant_blocks():
    """The task closes the loop through the real drive/coils/robot, fluid spheres, camera, tracker and servo."""
    from magctl.loops import Experiment, push_loop

    exp = Experiment("front", task=dict(kc=1.0, delta0=127 * UM, max_attempts=3, arrive_tol=20 * UM, servo="tuned"))
    status_, attempt, spheres = "controller/task.status", "controller/task.attempt", "plant/spheres.spheres"
    res = simulate(push_loop(exp), 1500, batch=2, seed=0, record=[status_, attempt, spheres])
    status = res[status_][:, -1]
    assert set(status) <= {CONVERGED, ATTEMPT_LIMIT}
    assert np.all(res[attempt][:, -1] >= 1)
    err = np.linalg.norm(res[spheres][:, -1, 0] - geometry("front")["goal"], axis=1)
    assert np.all(err[status == CONVERGED] < 75 * UM + 20 * UM)  # eq 12 on the estimate; tracker error margin


def test_front_then_side_assembly_runs_the_front_stage_unchanged_then_side_passes():
    """Fig 15's protocol: until the front stage ends, the composite is the one-push front assembly frame
    for frame; then the side stage (stage 2) takes over and closes the pair by eq 21."""
    start, spheres = (-1e-3, 0.0), [[0.0, 0.0], [800 * UM, 0.0]]
    front = FrontAssemblyTask(kc=1.0, max_attempts=1, eps_as=10 * UM, **EXACT)
    both = FrontThenSideAssemblyTask(front_attempts=1, ks=0.9, model="lin", clearance=850 * UM, eps_as=10 * UM,
                                     **EXACT)
    ref = simulate(ideal_loop(front, start, spheres), 1500, batch=2, seed=3)
    res = simulate(ideal_loop(both, start, spheres), 4000, batch=2, seed=3)
    name = both.name
    end = np.argmax(ref["front_assembly.status"] != RUNNING, axis=1)
    assert np.all(ref["front_assembly.status"][np.arange(2), end] == ATTEMPT_LIMIT)  # the pair separated
    for b in range(2):
        k = end[b]
        assert np.array_equal(res["spheres.spheres"][b, :k + 1], ref["spheres.spheres"][b, :k + 1])
        assert np.all(res[f"{name}.stage"][b, :k + 1] == 1) and np.all(res[f"{name}.stage"][b, k + 1:] == 2)
        assert res[f"{name}.status"][b, k] == RUNNING  # the hand-over is not an end
    assert np.all(res[f"{name}.status"][:, -1] == CONVERGED)
    s = res["tracker.spheres_est"][:, -1]
    assert np.all(np.linalg.norm(s[:, 1] - s[:, 0], axis=1) <= 220 * UM)
    assert np.all(res[f"{name}.attempt"][:, -1] >= 2)  # the front push and at least one side pass


def test_front_then_side_assembly_refuses_no_front_push():
    with pytest.raises(MagctlError, match="front_attempts"):
        FrontThenSideAssemblyTask(front_attempts=0)
