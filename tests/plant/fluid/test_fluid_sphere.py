"""The Spheres block: ports, Stokes vs inertial, position-not-velocity, contact, variability, errors."""

import numpy as np
import pytest

from magctl.core import Block, Diagram, Port, simulate
from magctl.core.errors import ParameterError, WiringError
from magctl.plant.fluid.params import sphere_params
from magctl.plant.fluid.scenarios import release_displacement, sidepush_curve
from magctl.plant.sphere import Spheres, integrate_inertial

R = 105e-6


class Prescribed(Block):
    """Robot moving at a constant velocity from a start point (test stand-in for the robot block)."""

    def __init__(self, start, velocity, heading=0.0):
        super().__init__("robot", outputs=[Port("position", (2,), "m"), Port("heading", (), "rad"),
                                           Port("velocity", (2,), "m/s")], feedthrough=False)
        self.start, self.v, self.h = np.asarray(start, float), np.asarray(velocity, float), float(heading)

    def initial_state(self, batch, rng=None):
        return {"p": np.tile(self.start, (batch, 1))}

    def output(self, state, u):
        b = len(state["p"])
        return {"position": state["p"].copy(), "heading": np.full(b, self.h), "velocity": np.tile(self.v, (b, 1))}

    def update(self, state, u):
        return {"p": state["p"] + self.v * self.dt}


def diagram(spheres, start, velocity, heading=0.0):
    robot = Prescribed(start, velocity, heading)
    return Diagram("rig", [robot, spheres],
                   connections=[("robot.position", "spheres.position"), ("robot.heading", "spheres.heading"),
                                ("robot.velocity", "spheres.velocity")],
                   outputs={"spheres": "spheres.spheres", "contact": "spheres.contact"})


def test_ports_and_batch_independence():
    s = Spheres(np.array([[0.0, 450e-6], [300e-6, -500e-6]]))
    assert s.inputs["position"].shape == (2,) and s.inputs["velocity"].unit == "m/s"
    assert s.outputs["spheres"].shape == (2, 2) and s.outputs["contact"].dtype == "bool"
    d = diagram(s, [-1e-3, 0.0], [4e-4, 0.0])
    one = simulate(d, 60, batch=1, seed=3)
    three = simulate(d, 60, batch=3, seed=3)
    assert one.outputs["spheres"].shape == (1, 60, 2, 2)
    assert np.allclose(three.outputs["spheres"][2], one.outputs["spheres"][0])
    moved = one.outputs["spheres"][0, -1] - one.outputs["spheres"][0, 0]
    assert moved[0, 0] > 1e-6 and moved[1, 0] > 1e-6          # dragged along the robot's motion


def test_displacement_depends_on_position_not_speed():
    # paper §III: in Stokes flow the robot's position, not its velocity, sets the displacement
    gaps = np.array([380e-6, 500e-6])
    slow = sidepush_curve(gaps, speed=0.2e-3)
    fast = sidepush_curve(gaps, speed=0.8e-3)
    assert np.allclose(slow.displacement, fast.displacement, rtol=0.02)


def test_inertial_and_inertia_free_agree():
    gap, speed, travel = 450e-6, 4e-4, 0.8e-3
    block = Spheres(np.array([[0.0, gap]]))

    def path(t):
        return np.array([-travel + speed * t, 0.0]), 0.0, np.array([speed, 0.0])

    t_end = 2 * travel / speed
    _, xy = integrate_inertial(block, np.array([0.0, gap]), path, t_end)
    stokes = sidepush_curve([gap], speed=speed, travel=travel)
    assert xy[-1, 0] == pytest.approx(stokes.along[0], rel=0.02)
    assert stokes.along[0] > 5e-6


def test_front_push_through_the_film_and_no_penetration():
    """The robot's face pushes the sphere ahead through the squeeze film: the sphere keeps the robot's speed
    with a film of microns between them (the film thins exponentially, on the scale 6πμA/ζU ≈ 0.2 s, and has
    not closed to rough contact in 3 s), and never penetrates the footprint."""
    s = Spheres(np.array([[400e-6, 0.0]]))
    res = simulate(diagram(s, [0.0, 0.0], [4e-4, 0.0]), 90, batch=1)
    t = np.arange(90) * s.dt
    sphere_x = res.outputs["spheres"][0, :, 0, 0]
    speed = (sphere_x[-1] - sphere_x[-11]) / (10 * s.dt)
    assert speed == pytest.approx(4e-4, rel=0.05)
    robot_x = 4e-4 * t
    rel = res.outputs["spheres"][0, :, 0, 0] - robot_x
    front = s.footprint[:, 0].max()
    assert rel[-1] > front - 0.2 * R      # sphere ahead of the robot, captured by the concave face
    from magctl.plant.outline import points_in_polygon, polygon_distance

    rel_xy = res.outputs["spheres"][0, :, 0, :] - np.column_stack([robot_x, np.zeros_like(t)])
    dist, _ = polygon_distance(rel_xy, s.footprint)
    assert not points_in_polygon(rel_xy, s.footprint).any()
    assert dist.min() > R - 15e-6            # at most one sub-step of travel inside before correction
    assert 0 < dist[-1] - R < 15e-6           # a thin film between face and sphere


def test_spheres_do_not_overlap():
    s = Spheres(np.array([[350e-6, -60e-6], [580e-6, 40e-6]]))
    res = simulate(diagram(s, [0.0, 0.0], [4e-4, 0.0]), 120, batch=1)
    xy = res.outputs["spheres"][0]
    d = np.linalg.norm(xy[:, 0] - xy[:, 1], axis=-1)
    assert d.min() > 2 * R - 1e-6


def test_release_follows_the_robot():
    d = release_displacement(retract=1.0e-3)
    assert 10e-6 < d[0] < 1.0e-3


def test_seeded_variability_is_per_trial(tmp_path):
    import dataclasses

    p = dataclasses.replace(sphere_params(), sticky_probability=0.5, release_scatter=0.3)
    s = Spheres(np.array([[0.0, 420e-6]]), params=p)
    assert s.uses_random
    d = diagram(s, [-0.6e-3, 0.0], [4e-4, 0.0])
    a = simulate(d, 90, batch=8, seed=11).outputs["spheres"][:, -1, 0, 0]
    b = simulate(d, 90, batch=8, seed=11).outputs["spheres"][:, -1, 0, 0]
    c = simulate(d, 90, batch=3, seed=11).outputs["spheres"][:, -1, 0, 0]
    assert np.array_equal(a, b) and np.allclose(a[:3], c)
    assert np.ptp(a) > 0.2 * np.abs(a).mean()


def test_bad_inputs():
    with pytest.raises(WiringError, match="initial_positions"):
        Spheres(np.zeros((3,)))
    with pytest.raises(ParameterError, match="drag_mode"):
        Spheres(np.zeros((1, 2)), drag_mode="comsol")
    with pytest.raises(ParameterError, match="roughness"):
        Spheres(np.zeros((1, 2)), roughness=-1.0)
    with pytest.raises(ValueError, match="gaps"):
        sidepush_curve([-1e-6])


def test_wires_to_the_actuated_robot():
    # contract of docs/interfaces.md: the robot's position/heading/velocity ports drive the spheres
    from magctl.plant.drive import actuated_robot

    plant = actuated_robot("plant", position=(-1e-3, 0.0), heading=0.0, variability=False)
    sph = Spheres(np.array([[0.0, 420e-6]]))
    d = Diagram("rig", [plant, sph],
                connections=[("plant.position", "spheres.position"), ("plant.heading", "spheres.heading"),
                             ("plant.velocity", "spheres.velocity")],
                inputs={"speed": "plant.speed", "heading": "plant.heading"},
                outputs={"spheres": "spheres.spheres", "position": "plant.position"})
    r = simulate(d, 120, batch=1, seed=1, inputs={"speed": 0.4e-3, "heading": 0.0})
    moved = r.outputs["spheres"][0, -1, 0] - r.outputs["spheres"][0, 0, 0]
    assert r.outputs["position"][0, -1, 0] > 0.5e-3     # the robot has passed the sphere
    assert 10e-6 < moved[0] < 200e-6                    # dragged forward by the flow, no contact
