"""Stick-slip robot block: heading dynamics, speed–frequency curve, viscosity, tilt, pose, variability.

Reference numbers are recomputed here from the raw values in models/*.toml with the closed forms
of docs/plant-actuator.md (rotational drag of a disc on an oil film, first-order rocking lag,
pivot geometry) and an ODE solver, not taken from the code under test.
"""

import tomllib

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from magctl.config import models_dir
from magctl.core import Diagram, simulate
from magctl.core.errors import WiringError
from magctl.core.random import TrialStreams
from magctl.plant.outline import robot_outline
from magctl.plant.robot import StickSlipRobot, load_robot

H = 1.0 / 30.0


def raw(name, table):
    with open(models_dir() / f"{name}.toml", "rb") as fh:
        return {k: v["value"] for k, v in tomllib.load(fh)[table].items()}


@pytest.fixture(scope="module")
def phys():
    r, f, body = raw("robot", "robot"), raw("fluid", "fluid"), raw("robot_geometry", "outline")
    mu = f["viscosity_cSt"] * 1e-6 * f["density_kg_m3"]
    L, T = body["length_um"] * 1e-6, body["thickness_um"] * 1e-6
    area = robot_outline().area              # checked against a pixel count in test_outline.py
    m = r["magnetization_kA_m"] * 1e3 * area * T
    a2 = area / np.pi
    zeta = np.pi * mu * a2**2 / (2 * r["film_gap_um"] * 1e-6)
    return {"mu": mu, "m": m, "zeta": zeta, "L": L, "c": r["pitch_drag_ratio_1"],
            "theta0": np.radians(r["break_angle_deg"]), "eta": r["slip_efficiency_1"]}


def run(robot, steps, bs, bo=0.0, f=0.0, batch=1, seed=0, state=None):
    st = robot.initial_state(batch, TrialStreams.for_trials(seed, range(batch))) if state is None else state
    u = {"b_static_delivered": np.broadcast_to(np.asarray(bs, float), (batch, 2)).copy(),
         "b_osc_delivered": np.full(batch, float(bo)), "freq_delivered": np.full(batch, float(f))}
    outs = []
    for _ in range(steps):
        outs.append({k: v.copy() for k, v in robot.output(st, u).items()})
        st = robot.update(st, u)
    outs.append(robot.output(st, u))
    return {k: np.stack([o[k] for o in outs], axis=1) for k in outs[0]}, st


def test_the_magnetization_keeps_the_calibrated_moment_per_filled_box():
    """robot.toml's source: M is 100 kA/m times the outline's fill of its box (the drive was calibrated with 60 kA/m
    over a 0.6 fill), so m/ζ ∝ M/φ, the heading rate and the rocking lag, are those of the calibration. An edit of
    the outline fails here until M is restated."""
    r, body = raw("robot", "robot"), raw("robot_geometry", "outline")
    fill = robot_outline().area / (body["length_um"] * body["width_um"] * 1e-12)
    assert r["magnetization_kA_m"] / fill == pytest.approx(60.0 / 0.6, rel=1e-12)


def test_heading_follows_field_like_the_ode(phys):
    b = 0.2e-3  # weak field: τ_ψ ≈ 90 ms, several frames
    robot = StickSlipRobot(variability=False)
    out, _ = run(robot, 10, [0.0, b])  # field at +90°, robot starts at 0
    tau = phys["zeta"] / (phys["m"] * b)
    sol = solve_ivp(lambda t, y: -np.sin(y - np.pi / 2) / tau, (0, 10 * H), [0.0], t_eval=np.arange(11) * H,
                    rtol=1e-10, atol=1e-12)
    assert out["heading"][0] == pytest.approx(sol.y[0], abs=1e-6)


def test_heading_small_step_time_constant(phys):
    b = 0.2e-3
    robot = StickSlipRobot(variability=False)
    psi_b = 0.05
    out, _ = run(robot, 4, [b * np.cos(psi_b), b * np.sin(psi_b)])
    err = psi_b - out["heading"][0]
    tau_fit = -H / np.mean(np.diff(np.log(err)))
    assert tau_fit == pytest.approx(phys["zeta"] / (phys["m"] * b), rel=2e-3)


def steady(robot, bs, bo, f):
    out, _ = run(robot, 3, [bs, 0.0], bo, f)
    return out["velocity"][0, -1, 0]


def test_speed_frequency_curve_rises_peaks_and_falls(phys):
    robot = StickSlipRobot(variability=False)
    bs, bo = 2e-3, 1.45e-3
    fc = phys["m"] * bs / (2 * np.pi * phys["c"] * phys["zeta"])  # rocking corner frequency
    f = np.geomspace(0.5, 4 * fc, 60)
    v = np.array([steady(robot, bs, bo, fi) for fi in f])
    k = int(np.argmax(v))
    assert 0 < k < len(f) - 1
    assert np.all(np.diff(v[: k + 1]) > 0) and np.all(np.diff(v[k:]) <= 0)
    assert 0.5 * fc < f[k] < 2 * fc
    # low frequency: a fixed step per cycle, v ∝ f; step from the pivot geometry
    step = phys["eta"] * phys["L"] * (np.cos(phys["theta0"]) - np.cos(np.arctan(bo / bs)))
    assert steady(robot, bs, bo, 0.01 * fc) == pytest.approx(0.01 * fc * step, rel=1e-3)
    # the robot stops where the attenuated rocking θ_qs/√(1+(f/fc)²) falls to the break-away angle
    f_stop = fc * np.sqrt((np.arctan(bo / bs) / phys["theta0"]) ** 2 - 1)
    assert steady(robot, bs, bo, 0.98 * f_stop) > 0
    assert steady(robot, bs, bo, 1.02 * f_stop) == 0


def test_viscosity_slows_the_robot():
    p = load_robot()
    f = np.geomspace(1, 500, 200)
    peaks = []
    for cst in (20, 50):
        robot = StickSlipRobot(params=p.with_viscosity(cst * 1e-6 * 950), variability=False)
        peaks.append(max(steady(robot, 2e-3, 1.45e-3, fi) for fi in f))
    # curve shape v = f·g(f/fc) with fc ∝ 1/µ: the peak speed scales as 1/µ
    assert peaks[1] / peaks[0] == pytest.approx(20 / 50, rel=0.02)


def test_no_aligning_field_no_motion():
    out, _ = run(StickSlipRobot(variability=False), 5, [0.0, 0.0], 1e-3, 10.0)
    assert np.all(out["position"] == 0)


def test_tilt_is_cycle_mean_of_rocking(phys):
    robot = StickSlipRobot(variability=False)
    out, _ = run(robot, 2, [2e-3, 0.0], 1.45e-3, 0.01)
    # quasi-static rock of amplitude atan(b_osc/b_static); mean |θ| of a sine is (2/π)·amplitude
    assert out["tilt"][0, -1] == pytest.approx(2 / np.pi * np.arctan(1.45 / 2.0), rel=1e-4)


def test_straight_motion_along_heading():
    robot = StickSlipRobot(variability=False, heading=0.7)
    bs = 2e-3 * np.array([np.cos(0.7), np.sin(0.7)])
    out, _ = run(robot, 60, bs, 1.45e-3, 10.0)
    d = out["position"][0, -1] - out["position"][0, 0]
    assert np.arctan2(d[1], d[0]) == pytest.approx(0.7, abs=1e-9)
    assert np.linalg.norm(out["velocity"][0, -1]) == pytest.approx(np.linalg.norm(d) / (60 * H), rel=1e-9)


def test_per_trial_initial_pose_and_errors():
    robot = StickSlipRobot(variability=False, position=[[1e-3, 0.0], [0.0, -1e-3]], heading=[0.0, np.pi / 2])
    st = robot.initial_state(2)
    out = robot.output(st, {})
    assert out["position"] == pytest.approx(np.array([[1e-3, 0.0], [0.0, -1e-3]]))
    assert out["heading"] == pytest.approx([0.0, np.pi / 2])
    st2 = robot.set_pose(st, position=[5e-4, 5e-4], heading=1.0)
    assert robot.output(st2, {})["position"] == pytest.approx(np.full((2, 2), 5e-4))
    assert robot.output(st, {})["position"][0, 0] == pytest.approx(1e-3)  # original state untouched
    with pytest.raises(WiringError, match="initial position"):
        robot.initial_state(3)
    with pytest.raises(WiringError, match="initial heading"):
        robot.set_pose(st, heading=[1.0, 2.0, 3.0])


def test_variability_is_seeded_per_trial_and_unbiased():
    robot = StickSlipRobot()
    assert robot.uses_random
    d = Diagram("d", [robot], inputs={"b": "robot.b_static_delivered", "bo": "robot.b_osc_delivered",
                                      "f": "robot.freq_delivered"}, outputs={"p": "robot.position"})
    u = {"b": [2e-3, 0.0], "bo": 1.45e-3, "f": 10.0}
    a = simulate(d, 90, batch=200, seed=3, inputs=u).outputs["p"]
    b = simulate(d, 90, batch=3, seed=3, inputs=u, trials=[5, 6, 7]).outputs["p"]
    assert np.array_equal(a[5:8], b)  # trial k does not depend on the batch
    assert np.std(a[:, -1, 0]) > 0
    det = simulate(Diagram("d", [StickSlipRobot(variability=False)], inputs={
        "b": "robot.b_static_delivered", "bo": "robot.b_osc_delivered", "f": "robot.freq_delivered"},
        outputs={"p": "robot.position"}), 90, batch=1, inputs=u).outputs["p"][0, -1, 0]
    # multiplicative noise of mean ~1 (clipping at 0 is 8 σ away): mean path within 3 standard errors
    cv = raw("robot", "robot")["step_cv_1"]
    se = det * cv / np.sqrt(89) / np.sqrt(200)
    assert abs(a[:, -1, 0].mean() - det) < 3 * se + 1e-12
