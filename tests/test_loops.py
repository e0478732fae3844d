"""The loop builders of magctl.loops: the plant linearised against a hand linearisation, the ports of
both halves, and clear errors for what cannot be built.

Hand linearisation of ``plant(scene, quiet)`` at rest under the aligning field ``B = (B₀, 0)``
(no oscillation, so the robot stands still and every state is at equilibrium):

* coil currents at DC are the minimum-norm allocation ``i = A⁺ [b_x, b_y, 0, G]`` of the actuation
  matrix (RL settles; the frame average equals the steady current), so ``∂currents/∂b_static = A⁺[:, :2]``;
* the robot's heading relaxes to the field's direction ``ψ = atan2(b_y, b_x)``, the camera sees it (noise
  off) and the Kalman tracker passes a constant with unit gain: ``∂heading_est/∂b_y = 1/B₀``, and a field
  along x does not turn it: ``∂heading_est/∂b_x = 0``;
* nothing moves the sphere: ``∂spheres_est/∂u = 0``.
"""

from __future__ import annotations

import numpy as np
import pytest

from magctl.core import Diagram, simulate
from magctl.core.errors import MagctlError, WiringError
from magctl.loops import COMMAND, PLANT_OUTPUTS, Scene, Variability, closed_loop, controller, plant
from magctl.plant._coilfield import load_coils
from magctl.plant.drive import load_drive

QUIET = Variability(camera_noise=False, robot_steps=False, release_scatter=0.0)
SCENE = Scene(robot=[1.0e-3, 1.8e-3], spheres=[[2.5e-3, 1.8e-3]])


def test_plant_linearises_to_the_hand_dc_gains_nested():
    b0 = load_drive().static_field
    outer = Diagram("rig", [plant(SCENE, QUIET)], inputs={n: f"plant.{n}" for n in COMMAND},
                    outputs={n: f"plant.{n}" for n in ("heading_est", "spheres_est", "currents", "robot_est")})
    u = {"b_static": [b0, 0.0], "b_osc": 0.0, "freq": 0.0}
    rest = simulate(outer, 60, inputs=u).final_state
    lin = outer.linearize(rest, u)
    # nested declared state, named by path
    for label in ("plant/coils.i[0]", "plant/robot.psi", "plant/tracker.x[0]", "plant/spheres.xy[0]"):
        assert label in lin.state_labels
    assert lin.input_labels == ["b_static[0]", "b_static[1]", "b_osc", "freq"]
    g = np.real(lin(np.exp(1j * 1e-6 * lin.dt)))     # the transfer matrix at (nearly) DC
    rows = {name: i for i, name in enumerate(lin.output_labels)}
    pinv = np.linalg.pinv(load_coils().actuation_matrix())
    currents = [rows[f"currents[{k}]"] for k in range(6)]
    np.testing.assert_allclose(g[np.ix_(currents, [0, 1])], pinv[:, :2], rtol=1e-6, atol=1e-9 * np.abs(pinv).max())
    assert g[rows["heading_est"], 1] == pytest.approx(1.0 / b0, rel=1e-5)
    assert abs(g[rows["heading_est"], 0]) < 1e-9 / b0
    np.testing.assert_allclose(g[[rows["spheres_est[0]"], rows["spheres_est[1]"]]], 0.0, atol=1e-12)


def test_the_halves_have_the_contract_ports():
    ctrl = controller("front-push", n_spheres=1, goal=[2.75e-3, 1.8e-3])
    assert set(ctrl.inputs) == {"robot_est", "spheres_est", "lost"}
    assert {*COMMAND, "status", "attempt"} <= set(ctrl.outputs)
    for kind in ("physics", "standin"):
        p = plant(SCENE, QUIET, kind=kind)
        assert set(p.inputs) == set(COMMAND) and set(p.outputs) == set(PLANT_OUTPUTS)
    loop = closed_loop(ctrl, plant(SCENE, QUIET))
    assert "controller/task.status" in {n for _, _, n in loop.schedule.signal_names()}


@pytest.mark.parametrize("build, words", [
    (lambda: controller("dance", n_spheres=0), "unknown task 'dance'"),
    (lambda: controller("front-push", n_spheres=1), "needs a goal"),
    (lambda: controller("goto", n_spheres=0), "needs a target"),
    (lambda: controller("goto", n_spheres=0, target=[0, 0], kc=1.0), "takes no options"),
    (lambda: controller("front-push", n_spheres=1, goal=[0, 0], wobble=3), "wobble"),
    (lambda: controller("assemble", n_spheres=2, goal=[0, 0]), "takes no goal"),
    (lambda: plant(SCENE, QUIET, kind="toy"), "plant 'toy'"),
    (lambda: plant(Scene(robot=[-1e-3, 0.0]), QUIET), "outside the camera's field of view"),
])
def test_what_cannot_be_built_is_named(build, words):
    with pytest.raises((MagctlError, WiringError), match=words):
        build()
