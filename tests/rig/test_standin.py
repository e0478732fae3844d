"""The stand-in plant's blocks against closed forms and the paper's numbers (eq 22, §IV-D)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from magctl import FRAME_PERIOD_S as T
from magctl.config import load_model
from magctl.core.random import TrialStreams
from magctl.core.simulation import simulate
from magctl.core.units import UM
from magctl.loops import Scene, plant
from magctl.plant.robot import load_robot, steady_speed
from magctl.plant.standin import (
    FieldGait,
    KinematicRobot,
    StandinSpheres,
    StandinTracker,
    StraightToTarget,
    standin_params,
)


def run(block, path, seed=0, batch=1):
    """Step the block along robot paths ``(T, 2)`` or ``(B, T, 2)``; returns the states after each step."""
    path = np.broadcast_to(path, (batch, *np.shape(path)[-2:]))
    state = block.initial_state(batch, TrialStreams.for_block(seed, list(range(batch)), "spheres"))
    out = []
    for k in range(path.shape[1]):
        state = block.update(state, {"position": path[:, k]})
        out.append(state)
    return out


def line(x0, x1, n, y=0.0):
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=1)


@pytest.mark.parametrize("gap_um", [300.0, 400.0, 600.0])
def test_a_straight_side_pass_displaces_the_sphere_by_eq_22(gap_um):
    block = StandinSpheres("spheres", [[0.0, gap_um * UM]], 250 * UM, side_range=800 * UM,
                           start_robot=(-2e-3, 0.0))
    s = run(block, line(-2e-3, 2e-3, 201))[-1]["s"][0, 0]
    expected = 1755 * np.exp(-0.009042 * gap_um) * UM  # eq 22, D_s in µm with D_g in µm
    np.testing.assert_allclose(s, [expected, gap_um * UM], rtol=1e-12, atol=1e-15)


def test_no_displacement_beyond_the_side_range_or_when_orbiting():
    block = StandinSpheres("spheres", [[0.0, 900 * UM]], 250 * UM, side_range=800 * UM, start_robot=(-2e-3, 0.0))
    np.testing.assert_array_equal(run(block, line(-2e-3, 2e-3, 201))[-1]["s"][0, 0], [0.0, 900 * UM])
    # a robot circling the sphere at 400 µm turns every frame: no straight pass, no eq 22 displacement
    a = np.linspace(-np.pi, np.pi, 121)  # 3° a frame
    block = StandinSpheres("spheres", [[0.0, 0.0]], 250 * UM, side_range=800 * UM, start_robot=(-400 * UM, 0.0))
    circle = 400 * UM * np.stack([np.cos(a), np.sin(a)], axis=1)
    np.testing.assert_array_equal(run(block, circle)[-1]["s"][0, 0], [0.0, 0.0])


@pytest.mark.parametrize("offset", [(0.0, 0.0), (1.0e-3, 1.8e-3), (3.7e-3, -2.1e-3)])
def test_retreating_robot_pulls_the_sphere_by_the_release_distance(offset):
    """Wherever the scene is: a sphere following the retreating robot sits at contact distance up to
    rounding, which must neither count as a new contact nor cut the release short."""
    contact = 250 * UM
    o = np.asarray(offset)
    block = StandinSpheres("spheres", [o + (1e-3, 0.0)], contact, release_mean=300 * UM, release_std=75 * UM,
                           start_robot=o)
    path = np.concatenate([line(0.0, 1.2e-3, 61), line(1.2e-3, 0.2e-3, 51)[1:]]) + o
    states = run(block, path, seed=3)
    s = np.array([st["s"][0, 0] for st in states]) - o
    after_push = s[60]
    assert after_push[0] == pytest.approx(1.2e-3 + contact, rel=1e-9)
    pulled = after_push[0] - s[-1][0]
    # the draw of the step when the retreat started: N(300, 75²) µm
    streams = TrialStreams.for_block(3, [0], "spheres")
    draws = [streams.standard_normal((), at=k)[0] for k in range(62)]
    assert pulled == pytest.approx(300 * UM + 75 * UM * draws[61], rel=1e-9)
    # the drawn amount is exposed: one release, of the pulled distance
    assert states[-1]["releases"][0] == 1
    assert states[-1]["last_release"][0] == pytest.approx(pulled, rel=1e-9)


def test_release_statistics_are_those_of_section_iv_d():
    """Over B seeded trials the pulled distances have the mean and spread of N(300, 75²) µm, to within
    4 standard errors of the sample size (mean: σ/√B; standard deviation: ≈ σ/√(2B))."""
    p = standin_params()
    release = load_model("push").release
    assert (p.release_mean, p.release_std) == (release.mean, release.std) == pytest.approx((300 * UM, 75 * UM))
    b = 1000
    block = StandinSpheres("spheres", [[1e-3, 0.0]], p.contact_distance, release_mean=p.release_mean,
                           release_std=p.release_std, start_robot=(0.0, 0.0))
    path = np.concatenate([line(0.0, 1.2e-3, 61), line(1.2e-3, 0.2e-3, 51)[1:]])
    states = run(block, path, seed=5, batch=b)
    pulled = states[60]["s"][:, 0, 0] - states[-1]["s"][:, 0, 0]
    np.testing.assert_allclose(pulled, states[-1]["last_release"], rtol=1e-9)
    mean, std = pulled.mean(), pulled.std(ddof=1)
    assert abs(mean - 300 * UM) < 4 * 75 * UM / np.sqrt(b)
    assert abs(std - 75 * UM) < 4 * 75 * UM / np.sqrt(2 * b)


def test_a_pushed_sphere_moves_the_one_it_runs_into_and_they_never_overlap():
    a = 105 * UM
    block = StandinSpheres("spheres", [[0.5e-3, 0.0], [0.8e-3, 0.0]], 250 * UM, sphere_radius=a,
                           start_robot=(0.0, 0.0))
    states = run(block, line(0.0, 1.0e-3, 101))
    s = states[-1]["s"][0]
    np.testing.assert_allclose(s[0], [1.25e-3, 0.0], rtol=1e-9)  # the driven sphere sits in the robot's notch
    np.testing.assert_allclose(s[1], [1.25e-3 + 2 * a, 0.0], rtol=1e-9)  # the other gave way to it
    gaps = [np.linalg.norm(st["s"][0, 1] - st["s"][0, 0]) for st in states]
    assert min(gaps) >= 2 * a * (1 - 1e-9)
    # without a radius the spheres pass through each other
    free = StandinSpheres("spheres", [[0.5e-3, 0.0], [0.8e-3, 0.0]], 250 * UM, start_robot=(0.0, 0.0))
    np.testing.assert_allclose(run(free, line(0.0, 1.0e-3, 101))[-1]["s"][0, 1], [1.25e-3, 0.0], rtol=1e-9)


def test_an_off_centre_push_keeps_the_lateral_offset():
    """The sphere is carried along the robot's path (the front notch), not deflected off it."""
    block = StandinSpheres("spheres", [[0.5e-3, 100 * UM]], 250 * UM, start_robot=(0.0, 0.0))
    s = run(block, line(0.0, 1.0e-3, 101))[-1]["s"][0, 0]
    np.testing.assert_allclose(s, [1.0e-3 + np.sqrt(250.0**2 - 100.0**2) * UM, 100 * UM], rtol=1e-9)


def test_kinematic_robot_integrates_speed_along_heading():
    """x[K] = start + T·Σ speed[k]·(cos h[k], sin h[k]); the heading is held while the speed is 0."""
    rng = np.random.default_rng(0)
    speed = rng.uniform(0, 400 * UM, (3, 50))
    speed[:, 20:25] = 0.0
    heading = rng.uniform(-np.pi, np.pi, (3, 50))
    start = np.array([1e-3, 2e-3])
    robot = KinematicRobot("robot", start=start, heading0=0.3)
    st = robot.initial_state(3)
    for k in range(50):
        out, old = robot.output(st, {}), st
        keep = {n: v.copy() for n, v in out.items()}
        snapshot = {n: v.copy() for n, v in old.items()}
        st = robot.update(old, {"speed": speed[:, k], "heading": heading[:, k]})
        assert st is not old
        for n in out:  # the outputs handed out and the old state are left untouched
            np.testing.assert_array_equal(out[n], keep[n])
        for n in snapshot:
            np.testing.assert_array_equal(old[n], snapshot[n])
        if 20 <= k < 25:
            np.testing.assert_array_equal(st["h"], heading[:, 19])
    expected = start + T * np.stack([(speed * np.cos(heading)).sum(1), (speed * np.sin(heading)).sum(1)], axis=1)
    np.testing.assert_allclose(robot.output(st, {})["position"], expected, rtol=1e-12)
    np.testing.assert_allclose(robot.output(st, {})["velocity"][:, 0], speed[:, -1] * np.cos(heading[:, -1]))


def test_field_gait_moves_the_robot_at_the_steady_stick_slip_speed():
    params = load_robot()
    gait = FieldGait("gait", params)
    b = np.array([[1e-3, 1e-3], [0.0, 0.0]])
    u = {"b_static_delivered": b, "b_osc_delivered": np.array([1.45e-3, 1.45e-3]),
         "freq_delivered": np.array([20.0, 20.0])}
    out = gait.output({}, u)
    v = steady_speed(params, np.hypot(*b[0])[None], u["b_osc_delivered"][:1], u["freq_delivered"][:1])[0]
    assert v > 0 and out["speed"][0] == pytest.approx(v)
    assert out["heading"][0] == pytest.approx(np.pi / 4) and out["steer"][0]
    assert out["speed"][1] == 0 and not out["steer"][1]
    # at rest in a static field (no rocking) the robot turns to the field without moving
    robot = KinematicRobot("robot", heading0=1.0, steer_input=True)
    st = robot.update(robot.initial_state(2), gait.output({}, {**u, "b_osc_delivered": np.zeros(2)}))
    np.testing.assert_allclose(st["h"], [np.pi / 4, 1.0])
    np.testing.assert_array_equal(st["x"], 0.0)


def test_straight_to_target_lands_on_the_target_at_the_capped_speed():
    servo = StraightToTarget("servo", v_max=1e-3)
    robot = KinematicRobot("robot", start=(0.0, 0.0))
    st = robot.initial_state(2)
    target = np.array([[300 * UM, 400 * UM], [300 * UM, 400 * UM]])
    cap = np.array([300 * UM, 5e-3])  # the second is capped by v_max
    for k in range(60):
        u = servo.output({}, {"target": target, "speed_cap": cap, "position": st["x"]})
        if k == 0:
            np.testing.assert_allclose(u["speed"], [300 * UM, 1e-3])
        st = robot.update(st, u)
    np.testing.assert_allclose(st["x"], target, atol=1e-18)
    stop = servo.output({}, {"target": target, "speed_cap": np.zeros(2), "position": np.zeros((2, 2))})
    np.testing.assert_array_equal(stop["speed"], 0.0)


def test_tracker_is_one_frame_late_and_reports_its_windows():
    trk = StandinTracker("tracker", 1, 5e-3, blackout=(2.5 * T, 4.5 * T), sphere_loss=(3.5 * T, np.inf))
    st = trk.initial_state(1)
    seen = []
    for k in range(6):
        p = np.array([[k * 1e-4, 0.0]])
        out = trk.output(st, {})
        seen.append((out["robot_est"][0, 0], bool(out["lost"][0]), bool(np.isnan(out["spheres_est"]).all())))
        st = trk.update(st, {"position": p, "heading": np.zeros(1), "spheres": np.zeros((1, 1, 2))})
    assert [s[0] for s in seen] == pytest.approx([0.0, 0.0, 1e-4, 2e-4, 3e-4, 4e-4])
    assert [s[1] for s in seen] == [False, False, False, True, True, False]  # shown at t = kT in [2.5T, 4.5T)
    assert [s[2] for s in seen] == [False, False, False, False, True, True]
    st = trk.update(st, {"position": np.array([[6e-3, 0.0]]), "heading": np.zeros(1),
                         "spheres": np.zeros((1, 1, 2))})
    assert trk.output(st, {})["lost"][0]  # outside the field of view


def test_the_rig_plant_is_the_composition():
    """``loops.plant(kind="standin")``: coils → gait → kinematic robot → spheres → tracker; a held field
    moves the robot at the steady speed along the field, seen by the tracker one frame late."""
    scene = Scene(robot=(1e-3, 1.8e-3), spheres=[[3e-3, 1.8e-3]])
    dia = plant(scene, kind="standin")
    assert {"coils", "gait", "robot", "spheres", "tracker"} <= set(dia.blocks)
    n = 30
    res = simulate(dia, n, inputs={"b_static": [1e-3, 0.0], "b_osc": 1.45e-3, "freq": 20.0}, seed=0,
                   record=["robot.position", "gait.speed", "tracker.robot_est"])
    speed = res["gait.speed"][0]
    assert np.all(speed[1:] > 0)
    x = res["robot.position"][0]
    np.testing.assert_allclose(x[-1, 0], 1e-3 + T * speed[:-1].sum(), rtol=1e-12)
    np.testing.assert_array_equal(x[:, 1], 1.8e-3)
    np.testing.assert_array_equal(res["tracker.robot_est"][0, 2:], x[1:-1])


def test_the_stand_in_imports_nothing_from_higher_layers():
    higher = ("magctl.rig", "magctl.control", "magctl.sensing", "magctl.loops", "magctl.stability", "magctl.studies")
    code = f"import sys, magctl.plant.standin; print(sorted(m for m in sys.modules if m.startswith({higher!r})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
