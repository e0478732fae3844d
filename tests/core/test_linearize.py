"""Linearisation and export: the package's own plant against hand linearisations, a linear diagram
against python-control's own interconnection, state names, and the errors.

Hand linearisation of the plant at the steady state ``B = (B₀, 0)``, ``b_osc``, ``f`` (variability off):

* coils: at DC the frame-average currents are ``i = A⁺ [b_x, b_y, 0, G]`` (the RL step is exact and
  linear), so ``∂i/∂b_static = A⁺[:, :2]`` and the delivered field equals the command;
* robot heading relaxes to the field direction ``ψ_B = atan2(b_y, b_x)``: ``∂ψ/∂b_y = 1/B₀``;
* velocity along the heading is the stick-slip speed ``v(|B|, b_osc, f)``: ``∂v_x/∂f = ∂v/∂f``,
  ``∂v_x/∂b_osc = ∂v/∂b_osc``, and ``v_y = v sin ψ`` gives ``∂v_y/∂b_y = v/B₀``;
* through the drive (fused ``ActuatedRobot``) the robot follows the commanded speed and heading:
  ``∂v_x/∂speed = 1``, ``∂ψ/∂heading = 1``, ``∂v_y/∂heading = v``.

The derivatives of ``v`` are central differences of :func:`magctl.plant._stickslip.speed`, the
model's steady-speed formula, taken here in the test.
"""

from __future__ import annotations

import control
import numpy as np
import pytest

from magctl.core import PI, Constant, Delay, Diagram, Gain, GaussianNoise, Integrator, Sum, simulate
from magctl.core.errors import MagctlError
from magctl.plant._stickslip import speed as steady_speed
from magctl.plant.coils import CoilActuator
from magctl.plant.drive import ActuatedRobot, actuated_robot, load_drive
from magctl.plant.robot import StickSlipRobot, load_robot

DT = 1 / 30


def _dc_without_position(sys: control.StateSpace) -> np.ndarray:
    """DC gain with the position states (pure integrators nothing else reads) taken out."""
    labels = list(sys.state_labels)
    pos = [i for i, lbl in enumerate(labels) if ".pos[" in lbl]
    rest = [i for i in range(len(labels)) if i not in pos]
    A, B, C, D = sys.A, sys.B, sys.C, sys.D
    assert pos, labels
    assert np.allclose(A[np.ix_(pos, pos)], np.eye(len(pos)))      # p[k+1] = p[k] + …
    assert np.allclose(A[np.ix_(rest, pos)], 0) and np.allclose(C[:, pos], 0)
    A2, B2, C2 = A[np.ix_(rest, rest)], B[rest], C[:, rest]
    return C2 @ np.linalg.solve(np.eye(len(rest)) - A2, B2) + D


def _plant_diagrams():
    """Coils → robot as a diagram nested in an outer one (inputs passed through)."""
    robot = load_robot()
    inner = Diagram(
        "plant", [CoilActuator("coils"), StickSlipRobot("robot", robot, variability=False)],
        [("coils.b_static_delivered", "robot.b_static_delivered"), ("coils.b_osc_delivered", "robot.b_osc_delivered"),
         ("coils.freq_delivered", "robot.freq_delivered")],
        inputs={"b_static": "coils.b_static", "b_osc": "coils.b_osc", "freq": "coils.freq"},
        outputs={"velocity": "robot.velocity", "heading": "robot.heading", "currents": "coils.currents",
                 "saturated": "coils.saturated"})
    outer = Diagram("outer", [inner], inputs={"b": "plant.b_static", "bo": "plant.b_osc", "f": "plant.freq"},
                    outputs={"velocity": "plant.velocity", "heading": "plant.heading", "currents": "plant.currents",
                             "saturated": "plant.saturated"})
    return robot, outer


def test_coils_and_robot_nested_linearise_to_the_hand_dc_gains():
    robot, outer = _plant_diagrams()
    drive = load_drive()
    b0, bo, f = drive.static_field, drive.osc_field, 40.0
    u = {"b": [b0, 0.0], "bo": bo, "f": f}
    steady = simulate(outer, 90, inputs=u).final_state   # coil currents settled
    lin = outer.linearize(steady, u)

    # states: the leaves' declared real state, nested path first
    assert lin.state_labels[:6] == [f"plant/coils.i[{e}]" for e in range(6)]
    assert "plant/robot.pos[0]" in lin.state_labels and "plant/robot.psi" in lin.state_labels
    assert lin.input_labels == ["b[0]", "b[1]", "bo", "f"]
    assert lin.output_labels[:3] == ["velocity[0]", "velocity[1]", "heading"]  # the flag is left out
    dc = _dc_without_position(lin)

    coils = CoilActuator("coils")
    np.testing.assert_allclose(dc[3:9, 0:2], coils.pinv[:, :2], rtol=1e-5, atol=1e-9)   # ∂i/∂b
    h = 1e-3
    v = steady_speed(robot, b0, bo, f)
    dv_df = (steady_speed(robot, b0, bo, f + h) - steady_speed(robot, b0, bo, f - h)) / (2 * h)
    dv_dbo = (steady_speed(robot, b0, bo + 1e-7, f) - steady_speed(robot, b0, bo - 1e-7, f)) / 2e-7
    dv_db = (steady_speed(robot, b0 + 1e-7, bo, f) - steady_speed(robot, b0 - 1e-7, bo, f)) / 2e-7
    assert v > 0 and dv_df > 0
    assert dc[0, 3] == pytest.approx(dv_df, rel=1e-4)       # ∂v_x/∂f
    assert dc[0, 2] == pytest.approx(dv_dbo, rel=1e-4)      # ∂v_x/∂b_osc
    assert dc[0, 0] == pytest.approx(dv_db, rel=1e-3)       # ∂v_x/∂b_x (|B| changes)
    assert dc[2, 1] == pytest.approx(1 / b0, rel=1e-5)      # ∂ψ/∂b_y
    assert dc[1, 1] == pytest.approx(v / b0, rel=1e-4)      # ∂v_y/∂b_y
    assert abs(dc[2, 0]) < 1e-6 * (1 / b0)                  # a field along x does not turn the robot


@pytest.mark.parametrize("fused", [True, False])
def test_actuated_robot_fused_and_wired_linearise_to_the_unicycle(fused):
    """The fused block (nested state) and the drive → coils → robot diagram give the same DC gains."""
    plant = (ActuatedRobot("plant", variability=False) if fused
             else actuated_robot("plant", variability=False))
    outer = Diagram("outer", [plant], inputs={"speed": "plant.speed", "heading": "plant.heading"},
                    outputs={"velocity": "plant.velocity", "heading": "plant.heading",
                             "saturated": "plant.saturated"})
    v0 = 3e-4
    u = {"speed": v0, "heading": 0.0}
    steady = simulate(outer, 90, inputs=u).final_state
    lin = outer.linearize(steady, u)
    assert lin.nstates == 6 + 2 + 1 + 2 + 1   # coil currents, position, heading, velocity, tilt
    prefix = "plant.coils.i" if fused else "plant/coils.i"
    assert f"{prefix}[0]" in lin.state_labels
    dc = _dc_without_position(lin)
    assert dc.shape == (3, 2)                 # saturated (bool) is not part of the model
    assert dc[0, 0] == pytest.approx(1.0, rel=2e-3)      # ∂v_x/∂speed
    assert dc[2, 1] == pytest.approx(1.0, rel=1e-5)      # ∂ψ/∂heading
    assert dc[1, 1] == pytest.approx(v0, rel=2e-3)       # ∂v_y/∂heading = v
    assert abs(dc[1, 0]) < 1e-9 and abs(dc[2, 0]) < 1e-9


def test_linear_diagram_export_matches_python_control_interconnect():
    kp, ki = 1.2, 0.4
    blocks = [Sum("e", "+-", shape=(2,)), PI("pi", kp, ki, shape=(2,)), Gain("k", 0.5, shape=(2,)),
              Integrator("p", shape=(2,), out_unit="1"), Delay("cam", 2, shape=(2,))]
    wires = [("e.y", "pi.e"), ("pi.u", "k.u"), ("k.y", "p.u"), ("p.y", "cam.u"), ("cam.y", "e.u1")]
    inner = Diagram("loop", blocks, wires, inputs={"r": "e.u0"}, outputs={"p": "p.y"})
    outer = Diagram("outer", [inner], inputs={"r": "loop.r"}, outputs={"p": "loop.p"})
    ours = outer.to_control()

    # python-control's own model of the same loop, built from transfer functions per axis
    z = control.tf([1.0, 0.0], [1.0], DT)
    pi = kp + ki * DT / (z - 1)
    plant = 0.5 * DT / (z - 1)
    loop = control.feedback(pi * plant, z**-2)
    ref = control.append(control.ss(loop), control.ss(loop))
    np.testing.assert_allclose(control.dcgain(ours), control.dcgain(ref), rtol=1e-9)
    np.testing.assert_allclose(np.sort_complex(control.poles(ours)), np.sort_complex(control.poles(ref)), atol=1e-9)
    w = np.array([0.1, 1.0, 10.0])
    np.testing.assert_allclose(control.frequency_response(ours, w).frdata,
                               control.frequency_response(ref, w).frdata, rtol=1e-9, atol=1e-12)
    # and the finite-difference linearisation of the same diagram agrees with the exact export
    lin = outer.linearize(outer.initial_state(1), {"r": [0.0, 0.0]})
    np.testing.assert_allclose(lin.A, ours.A, atol=1e-8)
    np.testing.assert_allclose(lin.B, ours.B, atol=1e-8)


def test_scalar_loop_matches_python_control_interconnect_by_names():
    """The same loop built with python-control alone: named subsystems joined by ``interconnect``."""
    kp, ki, g = 0.9, 0.3, 2.0
    d = Diagram("loop", [Sum("e", "+-"), PI("pi", kp, ki), Gain("k", g), Integrator("p", out_unit="1"),
                         Delay("cam", 3)],
                [("e.y", "pi.e"), ("pi.u", "k.u"), ("k.y", "p.u"), ("p.y", "cam.u"), ("cam.y", "e.u1")],
                inputs={"r": "e.u0"}, outputs={"p": "p.y", "u": "pi.u"})
    z = control.tf([1.0, 0.0], [1.0], DT)
    parts = [
        control.summing_junction(inputs=["r", "-ym"], output="e", dt=DT, name="sum"),
        control.ss(kp + ki * DT / (z - 1), inputs="e", outputs="u", name="pi"),
        control.ss(control.tf([g], [1.0], DT), inputs="u", outputs="v", name="k"),
        control.ss(DT / (z - 1), inputs="v", outputs="p", name="plant"),
        control.ss(z**-3, inputs="p", outputs="ym", name="cam"),
    ]
    ref = control.interconnect(parts, inplist=["r"], outlist=["p", "u"], dt=DT)
    ours = d.to_control()
    np.testing.assert_allclose(np.sort_complex(control.poles(ours)), np.sort_complex(control.poles(ref)), atol=1e-9)
    w = np.array([0.05, 0.5, 5.0, 50.0])
    np.testing.assert_allclose(control.frequency_response(ours, w).frdata,
                               control.frequency_response(ref, w).frdata, rtol=1e-9, atol=1e-12)
    assert sorted(ours.state_labels) == ["cam.u1", "cam.u2", "cam.u3", "p.x", "pi.I"]


def test_exported_state_space_names_its_states():
    inner = Diagram("inner", [Gain("g", 2.0), PI("pi", 1.0, 0.5)], [("g.y", "pi.e")], inputs={"x": "g.u"},
                    outputs={"u": "pi.u"})
    d = Diagram("d", [inner, Delay("cam", 2, shape=()), Integrator("i", shape=(2,)),
                      Constant("c", [1.0, 2.0], shape=(2,))],
                [("inner.u", "cam.u"), ("c.y", "i.u")], inputs={"x": "inner.x"},
                outputs={"y": "cam.y", "z": "i.y"})
    sys = d.to_control()
    assert sorted(sys.state_labels) == sorted(["inner/pi.I", "cam.u2", "cam.u1", "i.x[0]", "i.x[1]"])
    assert sys.output_labels == ["y", "z[0]", "z[1]"]
    # the names follow the states: the delay line's oldest entry, u[k−2], is the output
    k = sys.state_labels.index("cam.u2")
    assert sys.C[0, k] == 1.0


def test_pi_without_integral_gain_exports_a_static_gain():
    sys = PI("pi", 2.5, 0.0).to_control()
    assert sys.nstates == 0
    assert control.dcgain(sys) == pytest.approx(2.5)
    assert PI("pi", 2.5, 0.1).to_control().nstates == 1


def test_noise_blocks_linearise_about_the_noise_free_path():
    d = Diagram("n", [Gain("g", 3.0), GaussianNoise("noise", 0.5)], [("g.y", "noise.u")], inputs={"x": "g.u"},
                outputs={"y": "noise.y"})
    lin = d.linearize(d.initial_state(2, seed=1), {"x": 0.2})
    assert lin.D[0, 0] == pytest.approx(3.0)


def test_linearize_errors_are_clear():
    d = Diagram("d", [Gain("g", 2.0), Integrator("i")], [("g.y", "i.u")], inputs={"x": "g.u"}, outputs={"y": "i.y"})
    st = d.initial_state(1)
    with pytest.raises(MagctlError, match=r"no operating value for inputs \['x'\]"):
        d.linearize(st)
    with pytest.raises(MagctlError, match=r"has no inputs \['nope'\]"):
        d.linearize(st, {"x": 0.0, "nope": 1.0})
    with pytest.raises(MagctlError, match="must be a diagram state"):
        d.linearize({"x": 1.0}, {"x": 0.0})
    with pytest.raises(MagctlError, match="input 'x' has shape"):
        d.linearize(st, {"x": [[1.0, 2.0], [3.0, 4.0]]})
    bad = {**st, "leaves": [st["leaves"][0], {"x": st["leaves"][1]["x"], "extra": 1.0}]}
    with pytest.raises(MagctlError, match=r"state entries \['extra'\] are not declared"):
        d.linearize(bad, {"x": 0.0})
    flags = Diagram("f", [PI("pi", 1.0, 0.1, limit=1.0)], inputs={"e": "pi.e"}, outputs={"sat": "pi.saturated"})
    with pytest.raises(MagctlError, match="no real-valued output"):
        flags.linearize(flags.initial_state(1), {"e": 0.0})


def test_a_blocks_own_exact_jacobians_are_used_and_agree_with_finite_differences(monkeypatch):
    """KinematicRobot gives its Jacobians in closed form; linearize takes them instead of differencing."""
    import magctl.core.linearize as lz
    from magctl.plant.standin import KinematicRobot

    robot = KinematicRobot("robot", start=(1e-3, 2e-3), heading0=0.3)
    st = robot.initial_state(1)
    for speed, heading in ((3e-4, 0.7), (-2e-4, -1.2)):          # steering, and driven backwards (heading held)
        u = {"speed": np.array([speed]), "heading": np.array([heading])}
        exact = robot.jacobians(st, u)
        fd = lz.finite_difference_jacobians(robot, st, u)
        for a, b in zip(exact, fd, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-12)
        assert exact[0][2, 2] == (0.0 if speed > 0 else 1.0)
    d = Diagram("d", [robot], inputs={"speed": "robot.speed", "heading": "robot.heading"},
                outputs={"position": "robot.position"})

    def no_differences(*args, **kwargs):
        raise AssertionError("finite differences used although the block has exact Jacobians")

    monkeypatch.setattr(lz, "finite_difference_jacobians", no_differences)
    lin = d.linearize(d.initial_state(1), {"speed": 3e-4, "heading": 0.7})
    assert lin.B[0, 1] == pytest.approx(-DT * 3e-4 * np.sin(0.7))     # ∂x/∂ψ = −T s sin ψ
