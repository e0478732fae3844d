"""The robot's flow: rigid motion on its surface, linearity, map accuracy, cache invalidation."""

import dataclasses

import numpy as np
import pytest

from magctl.plant.fluid.flow import RobotFlow, robot_flow
from magctl.plant.fluid.geometry import RobotGeometry, polygon_distance

MU = 20e-6 * 950.0   # 20 cSt x 950 kg/m3 (models/fluid.toml)
H = 105.025e-6


@pytest.fixture(scope="module")
def flow():
    return robot_flow(RobotGeometry.from_params(), MU, H)


def test_rigid_translation_reproduced_on_the_surface(flow):
    g = flow.geometry
    check = dataclasses.replace(g, spacing=g.spacing * 0.77).collocation_points()   # between the nodes
    b = g.to_body(check)
    dist, _ = polygon_distance(b[:, :2], g.outline)
    faces = ((b[:, 2] < 1e-12) | (b[:, 2] > g.thickness - 1e-12)) & (dist > g.spacing)
    u = flow.velocity_exact(check[faces])
    for k in range(2):
        target = np.zeros(3)
        target[k] = 1.0
        err = np.abs(u[k] - target).max(axis=1)
        assert np.median(err) < 0.06
        assert np.percentile(err, 90) < 0.2


def test_no_slip_on_the_glass_away_from_the_robot(flow):
    pts = np.array([[x, y, 0.0] for x in (-800e-6, 0.0, 700e-6) for y in (-500e-6, 450e-6)])
    # per unit robot speed; the regularised direct term leaves a slip of O((eps/r)^2) of the local flow
    assert np.abs(flow.velocity_exact(pts)).max() < 2e-3


def test_map_lookup_matches_direct_summation(flow):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.2e-3, 1.2e-3, (300, 2))
    xy = xy[np.abs(xy[:, 1]) > 330e-6]
    v = rng.normal(size=(len(xy), 2)) * 4e-4
    exact = flow.velocity_exact(np.column_stack([xy, np.full(len(xy), H)]))
    direct = v[:, 0, None] * exact[0] + v[:, 1, None] * exact[1]
    mapped = flow.lookup(xy, v)
    scale = np.linalg.norm(v, axis=1).max()
    assert np.abs(mapped - direct).max() < 0.02 * scale
    # beyond the map the flow is summed directly
    far = np.array([[2.5e-3, 0.3e-3]])
    vf = np.array([[4e-4, 0.0]])
    assert np.allclose(flow.lookup(far, vf), vf[0, 0] * flow.velocity_exact(np.array([[2.5e-3, 0.3e-3, H]]))[0])


def test_flow_is_linear_in_velocity_and_decays(flow):
    xy = np.array([[0.0, 400e-6], [0.0, 800e-6], [0.0, 1200e-6]])
    v = np.array([[4e-4, 0.0]] * 3)
    u1, u2 = flow.lookup(xy, v), flow.lookup(xy, 2.5 * v)
    assert np.allclose(u2, 2.5 * u1)
    speed = u1[:, 0]
    assert 0 < speed[2] < speed[1] < speed[0] < 4e-4
    # mirror symmetry of the robot about its x-z plane
    assert np.allclose(flow.lookup(xy * [1, -1], v)[:, 0], speed, rtol=0.05)


def test_cache_keys_and_viscosity_independence(flow):
    assert robot_flow(flow.geometry, MU, H) is flow
    other = robot_flow(flow.geometry, 2 * MU, H)
    assert other is not flow
    # Stokes flow with prescribed boundary velocity does not depend on mu; the drag doubles
    xy = np.array([[100e-6, 420e-6]])
    v = np.array([[4e-4, 0.0]])
    assert np.allclose(other.lookup(xy, v), flow.lookup(xy, v), rtol=1e-6)
    assert np.allclose(other.drag(), 2 * flow.drag(), rtol=1e-6)


def test_bad_parameters():
    g = RobotGeometry.from_params()
    with pytest.raises(ValueError, match="viscosity"):
        RobotFlow(g, -1.0, H)
    with pytest.raises(ValueError, match="height"):
        RobotFlow(g, MU, 0.0)
    from magctl.core.errors import ParameterError

    with pytest.raises(ParameterError, match="raised_edge"):
        dataclasses.replace(g, raised_edge="left")


def test_symmetric_solve_equals_the_full_solve(monkeypatch):
    g = dataclasses.replace(RobotGeometry.from_params(), spacing=45e-6)
    assert g.is_symmetric()
    sym = RobotFlow(g, MU, H)
    monkeypatch.setattr(RobotGeometry, "is_symmetric", lambda self: False)
    full = RobotFlow(g, MU, H)
    assert np.allclose(sym.forces, full.forces, rtol=1e-9, atol=1e-12 * np.abs(full.forces).max())
