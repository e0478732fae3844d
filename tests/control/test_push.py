"""Push tasks end to end at 30 Hz on a kinematic stand-in plant, against the iteration-domain maps."""

import control
import numpy as np
import pytest
from standin_plant import StandInPlant

from magctl.control.learning import front_push_law, side_push_law
from magctl.control.push.assembly import AssemblyTask, FrontAssemblyTask
from magctl.control.push.front import FrontPushTask
from magctl.control.push.side import SidePushTask
from magctl.control.status import Status
from magctl.core.diagram import Diagram
from magctl.core.errors import MagctlError
from magctl.core.simulate import simulate
from magctl.stability import iteration as S

CONVERGED, ATTEMPT_LIMIT, TRACKING_LOST = Status.CONVERGED, Status.ATTEMPT_LIMIT, Status.TRACKING_LOST
SPHERE_LOST, STALLED = Status.SPHERE_LOST, Status.STALLED

UM = 1e-6
EXACT = {"arrive_tol": 0.1 * UM}  # the kinematic robot lands exactly on its targets


def loop(task, plant):
    n = task.name
    return Diagram("loop", [task, plant], [
        ("plant.robot_est", f"{n}.robot_est"), ("plant.spheres_est", f"{n}.spheres_est"), ("plant.lost", f"{n}.lost"),
        (f"{n}.target", "plant.target"), (f"{n}.speed_cap", "plant.speed_cap"),
    ])


def releases(res, n):
    cnt, last = res["plant.releases"], res["plant.last_release"]
    out = np.full((cnt.shape[0], n), 300 * UM)
    for b in range(cnt.shape[0]):
        v = last[b, np.flatnonzero(np.diff(cnt[b]) > 0) + 1][:n]
        out[b, : len(v)] = v
    return out


@pytest.mark.parametrize("kc,delta0", [(1.0, 0.0), (0.5, 127 * UM)])
def test_front_push_matches_the_attempt_map_trial_by_trial(kc, delta0):
    law = front_push_law(kc, delta0)
    task = FrontPushTask(goal=(750 * UM, 0.0), law=law, push_tol=0.1 * UM, **EXACT)
    res = simulate(loop(task, StandInPlant((-1e-3, 0.0), [[0.0, 0.0]])), 1800, batch=48, seed=7)
    status, att = res["front_push.status"][:, -1], res["front_push.attempt"][:, -1]
    assert set(status) <= {CONVERGED, ATTEMPT_LIMIT}
    pred = S.front_attempt_map(kc, delta0, releases(res, 10))["attempts"]
    np.testing.assert_array_equal(np.where(status == CONVERGED, att, -1), pred)
    # the same law object is the iteration-domain system
    assert control.poles(S.front_iteration_diagram(task.law).to_control()) == pytest.approx([1 - kc])
    # converged trials end within ε_p of the goal (eq 12)
    s = res["plant.spheres_est"][status == CONVERGED, -1, 0]
    assert np.all(np.hypot(s[:, 0] - 750 * UM, s[:, 1]) < 75 * UM)


def test_naive_front_push_hits_the_attempt_limit():
    task = FrontPushTask(goal=(750 * UM, 0.0), kc=0.0, delta0=0.0, max_attempts=4, **EXACT)
    res = simulate(loop(task, StandInPlant((-1e-3, 0.0), [[0.0, 0.0]])), 900, batch=8, seed=2)
    assert np.all(res["front_push.status"][:, -1] == ATTEMPT_LIMIT)
    assert np.all(res["front_push.attempt"][:, -1] == 4)
    # error stays near D_p,r (no compensation): §VI-A's naive steady error minus the servo overshoot
    s = res["plant.spheres_est"][:, -1, 0, 0]
    assert np.all(750 * UM - s > 75 * UM)


@pytest.mark.parametrize("ks,model", [(0.9, "lin"), (0.0, "exp")])
def test_side_push_converges_as_the_map_predicts(ks, model):
    task = SidePushTask(goal=(300 * UM, 0.0), ks=ks, model=model, clearance=850 * UM, **EXACT)
    res = simulate(loop(task, StandInPlant((-1e-3, 0.0), [[0.0, 0.0]])), 2600, batch=1)
    pred = S.side_attempt_map(ks, 300 * UM, model=model)
    assert res["side_push.status"][0, -1] == CONVERGED
    assert res["side_push.attempt"][0, -1] == pred["attempts"][0] <= 10
    s = res["plant.spheres_est"][0, -1, 0]
    assert np.hypot(s[0] - 300 * UM, s[1]) < 7.5 * UM


def test_side_push_with_the_printed_eq_18_sign_fails_explicitly():
    law = side_push_law(0.9, printed_sign=True)  # eq 18 exactly as printed
    task = SidePushTask(goal=(280 * UM, 0.0), law=law, model="lin", clearance=850 * UM, max_attempts=8, **EXACT)
    plant = StandInPlant((-1e-3, 0.0), [[0.0, 0.0]], side_range=600 * UM)
    res = simulate(loop(task, plant), 2600, batch=1)
    assert res["side_push.status"][0, -1] == ATTEMPT_LIMIT
    assert res["side_push.attempt"][0, -1] == 8
    # Δ grows every attempt and the gap sits on its lower bound: the over-push is reinforced
    a = res["side_push.attempt"][0]
    ends = np.flatnonzero(np.diff(a) > 0)
    assert np.all(np.diff(res["side_push.correction"][0, ends]) > 0)
    assert np.allclose(res["side_push.gap"][0, ends], 370 * UM)
    assert S.side_attempt_map(0.9, 280 * UM, model="lin", printed_sign=True)["attempts"][0] == -1


def test_side_push_assembly_terminates_by_eq_21():
    task = AssemblyTask(ks=0.9, model="lin", clearance=850 * UM, eps_as=10 * UM, **EXACT)
    plant = StandInPlant((-1e-3, 300 * UM), [[0.0, 0.0], [500 * UM, 0.0]])
    res = simulate(loop(task, plant), 3000, batch=1)
    assert res["assembly.status"][0, -1] == CONVERGED
    s1, s2 = res["plant.spheres_est"][0, -1]
    assert np.linalg.norm(s2 - s1) <= 210 * UM + 10 * UM
    assert 1 <= res["assembly.attempt"][0, -1] <= 30


def test_front_push_assembly_fails_as_in_the_paper():
    task = FrontAssemblyTask(kc=1.0, max_attempts=3, eps_as=10 * UM, **EXACT)
    plant = StandInPlant((-1e-3, 0.0), [[0.0, 0.0], [800 * UM, 0.0]])
    res = simulate(loop(task, plant), 1500, batch=4, seed=1)
    assert np.all(res["front_assembly.status"][:, -1] == ATTEMPT_LIMIT)
    s = res["plant.spheres_est"][:, -1]
    assert np.all(np.linalg.norm(s[:, 1] - s[:, 0], axis=1) > 220 * UM)


@pytest.mark.parametrize("plant_kw,task_kw,code", [
    ({"lost_from": 40}, {}, TRACKING_LOST),
    ({"sphere_lost_from": 40}, {}, SPHERE_LOST),
    ({"v_max": 1e-6}, {"phase_timeout_frames": 60}, STALLED),
])
def test_failure_modes_end_the_task(plant_kw, task_kw, code):
    task = FrontPushTask(goal=(750 * UM, 0.0), **task_kw)
    # a vanished sphere is reported as NaN, which the finiteness check would stop on
    res = simulate(loop(task, StandInPlant((-1e-3, 0.0), [[0.0, 0.0]], **plant_kw)), 200, batch=2, check_finite=False)
    status = res["front_push.status"][:, -1]
    assert np.all(status == code)
    assert np.all(res["front_push.speed_cap"][:, -1] == 0)


def test_batch_independence_and_outputs_not_mutated():
    task = FrontPushTask(goal=(750 * UM, 0.0), kc=1.0, **EXACT)
    dia = loop(task, StandInPlant((-1e-3, 0.0), [[0.0, 0.0]]))
    big = simulate(dia, 600, batch=6, seed=4)
    one = simulate(dia, 600, batch=1, seed=4, trials=[3])
    np.testing.assert_array_equal(big["front_push.target"][3], one["front_push.target"][0])
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


@pytest.mark.slow
def test_front_push_runs_on_the_plant_blocks():
    """The task closes the loop through the real drive/coils/robot, fluid spheres, camera, tracker and servo."""
    from magctl.loops import Experiment, geometry, push_loop

    exp = Experiment("front", task=dict(kc=1.0, delta0=127 * UM, max_attempts=3, arrive_tol=20 * UM, servo="tuned"))
    status_, attempt, spheres = "controller/task.status", "controller/task.attempt", "plant/spheres.spheres"
    res = simulate(push_loop(exp), 1500, batch=2, seed=0, record=[status_, attempt, spheres])
    status = res[status_][:, -1]
    assert set(status) <= {CONVERGED, ATTEMPT_LIMIT}
    assert np.all(res[attempt][:, -1] >= 1)
    err = np.linalg.norm(res[spheres][:, -1, 0] - geometry("front")["goal"], axis=1)
    assert np.all(err[status == CONVERGED] < 75 * UM + 20 * UM)  # eq 12 on the estimate; tracker error margin
