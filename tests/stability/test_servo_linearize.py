"""``linearize`` on the package's own servo loop: the nonlinear polar Servo block (speed and heading from
the PI law), the kinematic robot, the camera's two frames of lag and its pixel noise, linearised about a
moving operating point, against the hand linearisation and python-control's margins.

Hand linearisation. At error ``e = (e₀, 0)``, ``e₀ > 0``, integral 0, unsaturated: the command
``c = Kp e + Ki I`` has ``speed = ‖c‖``, ``heading = atan2(c_y, c_x)``, so ``∂speed/∂c_x = 1`` and
``∂heading/∂c_y = 1/(Kp e₀)``; the robot moves ``x ← x + T speed (cos h, sin h)``, so along x it adds
``T·Δspeed`` and along y ``T·speed·Δh = T·Δc_y``. Both axes are therefore the one-axis loop of the
paper's servo, ``L(z) = (Kp + Ki T/(z − 1)) · T/(z − 1) · z⁻ᵈ``, whose closed-loop characteristic
polynomial is ``z^d (z − 1)² + T (Kp (z − 1) + Ki T) = 0``. Noise blocks linearise as their noise-free
path (σ·0).
"""

from __future__ import annotations

import control
import numpy as np
import pytest

from magctl.control.servo import Servo, servo_params
from magctl.core import Delay, Diagram, GaussianNoise
from magctl.plant.standin import KinematicRobot

T = 1 / 30
D = 2
E0 = 100e-6        # 100 µm from the target: Kp·e₀ = 350 µm/s, under the 400 µm/s limit


def _servo(setting):
    return Servo("servo", params=servo_params(setting))


def _loop(setting, *, closed: bool) -> Diagram:
    blocks = [_servo(setting), KinematicRobot("robot", start=(0.0, 0.0)),
              Delay("camera", D, shape=(2,), unit="m"), GaussianNoise("pixels", 3e-6, shape=(2,), unit="m")]
    conns = [("servo.speed", "robot.speed"), ("servo.heading", "robot.heading"), ("robot.position", "camera.u"),
             ("camera.y", "pixels.u")]
    inputs = {"target": "servo.target"}
    if closed:
        conns.append(("pixels.y", "servo.robot_est"))
    else:
        inputs["measured"] = "servo.robot_est"          # the loop broken at the measurement
    return Diagram("servo_loop", blocks, conns, inputs=inputs, outputs={"measured": "pixels.y"})


def _hand_poles(kp, ki):
    # z^d (z − 1)² + T (Kp (z − 1) + Ki T): coefficients in descending powers
    z_d = np.zeros(D + 1)
    z_d[0] = 1.0
    poly = np.polymul(z_d, [1.0, -2.0, 1.0])
    tail = np.zeros_like(poly)
    tail[-2:] = [T * kp, T * (ki * T - kp)]
    return np.roots(poly + tail)


def _hand_loop(kp, ki):
    z = control.tf([1, 0], [1], T)
    return (kp + ki * T / (z - 1)) * T / (z - 1) * z ** (-D)


@pytest.mark.parametrize("setting", ["paper", "tuned"])
def test_closed_servo_loop_linearises_to_the_hand_poles(setting):
    p = servo_params(setting)
    loop = _loop(setting, closed=True)
    state = loop.initial_state(1, seed=4)           # the noise stream is there; linearize switches it off
    lin = loop.linearize(state, {"target": [E0, 0.0]})
    assert lin.output_labels == ["measured[0]", "measured[1]"]
    poles = np.linalg.eigvals(lin.A)
    loop_poles = poles[np.abs(poles) > 1e-9]        # heading and velocity memories are poles at 0
    want = _hand_poles(p.kp, p.ki)
    want = want[np.abs(want) > 1e-9]
    assert len(loop_poles) == 2 * len(want)         # x and y: the same loop twice
    for w in want:
        assert np.sum(np.abs(loop_poles - w) < 1e-6) == 2, (w, loop_poles)
    # stable; with Ki = 0 the servo's integral still sums the error but nothing reads it: its two modes at
    # z = 1 are unobservable, and the minimal realisation drops them
    at_one = np.abs(poles - 1) < 1e-9
    assert np.all(np.abs(poles[~at_one]) < 1 - 1e-3)
    assert at_one.sum() == (2 if p.ki == 0 else 0)
    n = lin.nstates
    assert np.linalg.matrix_rank(np.vstack([lin.A - np.eye(n), lin.C])) == n - at_one.sum()   # PBH: unobservable


@pytest.mark.parametrize("setting", ["paper", "tuned"])
def test_open_servo_loop_has_python_controls_margins_of_the_hand_loop(setting):
    p = servo_params(setting)
    loop = _loop(setting, closed=False)
    u = {"target": [E0, 0.0], "measured": [0.0, 0.0]}
    lin = loop.linearize(loop.initial_state(1), u)
    i_meas = [lin.input_labels.index("measured[0]"), lin.input_labels.index("measured[1]")]
    hand = _hand_loop(p.kp, p.ki)
    gm_h, pm_h, _, wc_h = control.margin(hand)
    omega = np.logspace(-2, np.log10(np.pi / T), 3000)
    zs = np.exp(1j * omega * T)
    for axis in (0, 1):
        L = -control.ss(lin.A, lin.B[:, [i_meas[axis]]], lin.C[[axis]], lin.D[[axis]][:, [i_meas[axis]]], dt=T)
        # the same frequency response as the hand loop at every frequency up to Nyquist …
        np.testing.assert_allclose(L(zs), hand(zs), rtol=1e-7)
        # … and python-control reads the same margins off it (from the frequency response: the linearised
        # model also carries the unobservable integral and heading memories, whose poles at z = 1 and 0
        # make the polynomial route ill-conditioned)
        gm, pm, _, wc = control.margin(control.frd(L, omega))
        assert gm == pytest.approx(gm_h, rel=1e-3)
        assert pm == pytest.approx(pm_h, rel=1e-3)
        assert wc == pytest.approx(wc_h, rel=1e-3)
    # the axes do not couple: a y measurement error does not move x
    x_from_y = control.ss(lin.A, lin.B[:, [i_meas[1]]], lin.C[[0]], lin.D[[0]][:, [i_meas[1]]], dt=T)
    assert np.allclose(control.impulse_response(x_from_y, T=np.arange(40) * T).outputs, 0.0, atol=1e-9)
