"""Linear blocks against closed forms and python-control; linearisation of nonlinear blocks."""

import control
import numpy as np

from magctl.core import PI, Block, Constant, Delay, Diagram, Integrator, NormSaturation, Port, Sum, simulate
from magctl.core.block import StateVar

DT = 1 / 30


def test_delay_is_z_to_the_minus_d():
    assert np.allclose(control.poles(Delay("z", 3).to_control()), 0)
    pulse = control.forced_response(Delay("z", 3).to_control(), np.arange(6) * DT, [1, 0, 0, 0, 0, 0])
    assert np.allclose(np.squeeze(pulse.outputs), [0, 0, 0, 1, 0, 0])


def test_pi_transfer_function():
    kp, ki = 1.5, 0.3
    got = control.tf(PI("pi", kp, ki).to_control())
    z = control.tf([1, 0], [1], dt=DT)
    want = kp + ki * DT / (z - 1)
    w = np.exp(1j * np.linspace(0.1, 3, 7))
    assert np.allclose(got(w), want(w))


def test_pi_anti_windup_holds_integral_while_saturated():
    """A long saturated stretch must not wind up: once the error shrinks the output leaves saturation at once."""
    pi = PI("pi", 1.0, 2.0, limit=1.0, norm=False)
    d = Diagram("d", [pi], inputs={"e": "pi.e"}, outputs={"u": "pi.u", "sat": "pi.saturated"})
    e = np.r_[np.full(300, 10.0), np.full(30, 0.1)]
    res = simulate(d, e.size, inputs={"e": e})
    u = res["u"][0]
    assert np.all(np.abs(u) <= 1.0 + 1e-12)
    assert res["sat"][0, :300].all()
    # the integral held at 0 during saturation: right after, u = kp*0.1 + ki*I with I tiny
    assert abs(u[300] - 0.1) < 1e-12
    assert not res["sat"][0, 300:].any()


def test_norm_saturation_keeps_direction():
    blk = NormSaturation("s", 1.0)
    y = blk.output({}, {"u": np.array([[3.0, 4.0], [0.3, 0.4]])})
    assert np.allclose(y["y"], [[0.6, 0.8], [0.3, 0.4]])
    assert y["saturated"].tolist() == [True, False]


class Pendulum(Block):
    """x = (θ, ω); θ+ = θ + T ω; ω+ = ω − T (g sin θ) + T u — nonlinear, no Jacobian supplied."""

    def __init__(self):
        super().__init__("pend", inputs=[Port("u")], outputs=[Port("theta")], feedthrough=False)

    def state_vars(self):
        return (StateVar("x", (2,), symbol="(θ, ω)"),)

    def initial_state(self, batch, rng=None):
        return {"x": np.zeros((batch, 2))}

    def output(self, state, u):
        return {"theta": state["x"][:, 0]}

    def update(self, state, u):
        th, om = state["x"][:, 0], state["x"][:, 1]
        return {"x": np.stack([th + DT * om, om - DT * 9.81 * np.sin(th) + DT * u["u"]], axis=1)}


def test_linearize_by_finite_differences_matches_analytic():
    pend = Pendulum()
    d = Diagram("p", [pend], inputs={"u": "pend.u"}, outputs={"theta": "pend.theta"})
    state = d.initial_state(1)
    theta0 = 0.4
    state["leaves"][0]["x"][0] = [theta0, 0.0]
    lin = d.linearize(state, {"u": 9.81 * np.sin(theta0)})
    A_true = np.array([[1, DT], [-DT * 9.81 * np.cos(theta0), 1]])
    assert np.allclose(lin.A, A_true, atol=1e-6)
    assert np.allclose(lin.B.ravel(), [0, DT], atol=1e-8)
    assert np.allclose(lin.C, [[1, 0]])


def test_nonlinear_loop_linearized_about_unsaturated_point_equals_linear_loop():
    kp, ki = 1.5, 0.3

    def loop(with_sat):
        blocks = [Constant("r", [1.0, 0.5], shape=(2,)), Sum("e", "+-", shape=(2,)),
                  PI("pi", kp, ki, shape=(2,), limit=100.0 if with_sat else None),
                  Integrator("p", shape=(2,), out_unit="1"), Delay("cam", 2, shape=(2,))]
        wires = [("r.y", "e.u0"), ("cam.y", "e.u1"), ("e.y", "pi.e"), ("p.y", "cam.u")]
        if with_sat:
            blocks.append(NormSaturation("sat", 100.0))
            wires += [("pi.u", "sat.u"), ("sat.y", "p.u")]
        else:
            wires += [("pi.u", "p.u")]
        return Diagram("loop", blocks, wires, outputs={"p": "p.y"})

    lin = loop(True).linearize(loop(True).initial_state(1))
    exact = loop(False).to_control()
    assert np.allclose(np.sort_complex(control.poles(lin)), np.sort_complex(control.poles(exact)), atol=1e-6)
