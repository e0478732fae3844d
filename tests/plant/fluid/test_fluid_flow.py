"""The robot's flow (boundary elements with Blake's tensor): rigid motion on its surface, no slip on the
glass, the maps and their off-map continuation, caches, and the bounded oil layers (lid, free surface)."""

import dataclasses

import numpy as np
import pytest

from magctl.plant.fluid import bem
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.flow import RobotFlow, robot_flow
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.outline import points_in_polygon

MU = 20e-6 * 950.0   # 20 cSt x 950 kg/m3 (models/fluid.toml)
H = 105.025e-6
UNIT = np.eye(3)[:2]


@pytest.fixture(scope="module")
def flow():
    return robot_flow(RobotGeometry.from_params(), MU, H, Domain())


@pytest.fixture(scope="module")
def coarse():
    """A coarser mesh of the same robot, for the bounded layers' boundary conditions."""
    return RobotGeometry.from_params().refined(2.0)


@pytest.fixture(scope="module")
def tiny():
    """A very coarse mesh, for the algebra (linearity in μ, symmetry, caches)."""
    return RobotGeometry.from_params().refined(2.5)


def _on_panels(tris, idx, seed):
    """One random point on each panel ``idx`` (uniform barycentric), never a centroid."""
    bc = np.random.default_rng(seed).dirichlet([1.0, 1.0, 1.0], size=len(idx))
    return np.einsum("tk,tki->ti", bc, tris[idx])


def test_surface_mesh_is_closed_and_outward():
    g = RobotGeometry.from_params()
    half = g.surface_mesh()
    full = np.concatenate([half, bem.mirrored(half, 1)])
    n, a = bem.normals(full), bem.areas(full)
    assert np.abs((n * a[:, None]).sum(axis=0)).max() < 1e-9 * a.sum()       # closed surface
    volume = (bem.centroids(full) * n * a[:, None]).sum() / 3.0               # divergence theorem, outward
    x, y = g.outline[:, 0], g.outline[:, 1]
    outline_area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert volume == pytest.approx(outline_area * g.thickness, rel=1e-9)
    assert full[..., 2].min() == pytest.approx(g.clearance, rel=1e-9)
    # refined towards the gap: panels touching the lowest edge are no larger than wall_ratio x their height
    low = full[..., 2].min(axis=1) < 2 * g.clearance
    edge = np.linalg.norm(full[low] - np.roll(full[low], 1, axis=1), axis=2).max(axis=1)
    assert edge.max() < 4 * g.wall_ratio * g.clearance + g.gap_size


def test_rigid_translation_between_collocation_nodes(flow):
    robot = np.nonzero(flow.robot_panels)[0][::11]
    pts = _on_panels(flow.tris, robot, 3)
    u = bem.layer_velocity(pts, flow.tris, flow.density, flow.viscosity, own=robot)
    for k in range(2):
        err = np.linalg.norm(u[k] - UNIT[k], axis=1)
        assert np.median(err) < 0.01
        assert np.percentile(err, 90) < 0.05
        assert err.max() < 0.35           # worst at the rims over the 2 um gap


def test_no_slip_on_the_glass_around_and_under_the_robot(flow):
    xs = np.linspace(-450e-6, 450e-6, 37)
    xx, yy = np.meshgrid(xs, xs)
    plane = np.column_stack([xx.ravel(), yy.ravel()])
    # and densely under the resting (rear) corners, where the edge is 2 um above the glass
    foot = flow.geometry.footprint
    corners = foot[np.argsort(foot[:, 0])[:2]]
    fine = np.linspace(-8e-6, 8e-6, 9)
    near = (corners[:, None, None, :] + np.stack(np.meshgrid(fine, fine), -1)[None]).reshape(-1, 2)
    plane = np.vstack([plane, near])
    assert points_in_polygon(near, foot).any()
    on = flow.velocity_exact(np.column_stack([plane, np.zeros(len(plane))]))
    assert np.abs(on).max() < 1e-12
    above = flow.velocity_exact(np.column_stack([plane, np.full(len(plane), 10e-9)]))
    assert np.abs(above).max() < 0.01          # 10 nm above the glass, per unit robot speed


def test_map_lookup_matches_the_panel_integrals(flow):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.2e-3, 1.2e-3, (300, 2))
    xy = xy[np.abs(xy[:, 1]) > 330e-6]
    v = rng.normal(size=(len(xy), 2)) * 4e-4
    exact = flow.velocity_exact(np.column_stack([xy, np.full(len(xy), H)]))
    direct = v[:, 0, None] * exact[0] + v[:, 1, None] * exact[1]
    mapped = flow.lookup(xy, v)
    scale = np.linalg.norm(v, axis=1).max()
    assert np.abs(mapped - direct).max() < 0.02 * scale


def test_off_map_point_forces_continue_the_map(flow):
    lim = flow.gx[-1]
    pts = np.array([[lim * 1.0001, y, H] for y in (0.0, 0.5e-3, 1.4e-3)]
                   + [[x, lim * 1.0001, H] for x in (-1.4e-3, 0.0, 0.7e-3)]
                   + [[2.5e-3, 0.3e-3, H], [0.0, 3e-3, H]])
    # per unit robot speed: the gathered point forces against the panel integrals
    assert np.abs(flow.velocity_far(pts) - flow.velocity_exact(pts)).max() < 1e-4
    # the look-up is continuous across the map's edge
    v = np.array([[1.0, 0.3]])
    pairs = (([lim * 0.99999, 0.2e-3], [lim * 1.00001, 0.2e-3]), ([0.3e-3, lim * 0.99999], [0.3e-3, lim * 1.00001]))
    for a, b in pairs:
        ua, ub = flow.lookup(np.array([a]), v), flow.lookup(np.array([b]), v)
        assert np.abs(ua - ub).max() < 2e-5
    assert flow.eps == 0.0


def test_flow_is_linear_in_velocity_and_decays(flow):
    xy = np.array([[0.0, 400e-6], [0.0, 800e-6], [0.0, 1200e-6]])
    v = np.array([[4e-4, 0.0]] * 3)
    u1, u2 = flow.lookup(xy, v), flow.lookup(xy, 2.5 * v)
    assert np.allclose(u2, 2.5 * u1)
    speed = u1[:, 0]
    assert 0 < speed[2] < speed[1] < speed[0] < 4e-4
    # mirror symmetry of the robot about its x-z plane
    assert np.allclose(flow.lookup(xy * [1, -1], v)[:, 0], speed, rtol=1e-9)


def test_drag_opposes_the_motion(flow):
    d = flow.drag()
    assert d[0, 0] < 0 and d[1, 1] < 0
    assert abs(d[0, 1]) < 1e-9 * abs(d[0, 0]) and abs(d[1, 0]) < 1e-9 * abs(d[1, 1])


def test_viscosity_independence(tiny):
    a = RobotFlow(tiny, MU, H, disk_cache=False)
    b = RobotFlow(tiny, 2 * MU, H, disk_cache=False)
    # Stokes flow with prescribed boundary velocity does not depend on mu; the drag doubles
    assert np.allclose(a.maps, b.maps, rtol=1e-9, atol=1e-13)
    assert np.allclose(b.drag(), 2 * a.drag(), rtol=1e-9)


def test_memory_and_disk_caches(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv("MAGCTL_CACHE", str(tmp_path))
    first = RobotFlow(tiny, MU, H)
    assert len(list((tmp_path / "robot_flow").glob("*.npz"))) == 1

    def no_solve(self):
        raise AssertionError("solved although the disk cache holds this key")

    monkeypatch.setattr(RobotFlow, "_solve", no_solve)
    again = RobotFlow(tiny, MU, H)
    for name in ("maps", "density", "points", "forces", "inside"):
        assert np.array_equal(getattr(again, name), getattr(first, name))
    for changed in (dict(height=1.01 * H), dict(viscosity=2 * MU), dict(domain=Domain("lid", 1e-3)),
                    dict(geometry=dataclasses.replace(tiny, clearance=3e-6))):
        kw = dict(geometry=tiny, viscosity=MU, height=H) | changed
        with pytest.raises(AssertionError, match="solved"):
            RobotFlow(**kw)


def test_memory_cache_is_keyed_by_every_input(flow):
    assert robot_flow(flow.geometry, MU, H, Domain()) is flow
    assert robot_flow(flow.geometry, MU, H) is robot_flow(flow.geometry, MU, H, Domain.from_params())
    assert robot_flow(flow.geometry, MU, H) is not flow       # models/fluid.toml [domain] is a lid


def test_mirror_solve_equals_the_full_solve(tiny):
    half = RobotFlow(tiny, MU, H, disk_cache=False)
    s = len(half.tris)
    full = bem.PanelSet(half.tris, np.arange(s), np.ones((s, 3)), np.zeros(s, int), s)
    rhs = np.zeros((2, s, 3))
    rhs[0, :, 0] = rhs[1, :, 1] = 1.0
    q = bem.solve(full, rhs, MU, deflate=True)
    # the two deflations may leave different multiples of the (near-)null pressure mode, which carries no flow
    assert np.allclose(q, half.density, rtol=1e-4, atol=1e-6 * np.abs(half.density).max())
    pts = np.array([[250e-6, 0.0, H], [0.0, 300e-6, H], [-200e-6, -260e-6, 50e-6]])
    u_full = bem.layer_velocity(pts, half.tris, q, MU)
    assert np.allclose(u_full, half.velocity_exact(pts), rtol=1e-7, atol=1e-9)


def test_bad_parameters():
    g = RobotGeometry.from_params()
    with pytest.raises(ValueError, match="viscosity"):
        RobotFlow(g, -1.0, H)
    with pytest.raises(ValueError, match="height"):
        RobotFlow(g, MU, 0.0)
    with pytest.raises(ValueError, match="below the oil depth"):
        RobotFlow(g, MU, H, Domain("lid", 0.5 * H))
    with pytest.raises(ValueError, match="finite-element"):
        RobotFlow(g, MU, H, Domain("box", 1e-3, 3e-3, 1.5e-3))
    from magctl.core.errors import ParameterError

    with pytest.raises(ParameterError, match="raised_edge"):
        dataclasses.replace(g, raised_edge="left")
    with pytest.raises(ParameterError, match="panel sizes"):
        dataclasses.replace(g, edge_size=2 * g.panel_size)
    with pytest.raises(ParameterError, match="clearance"):
        dataclasses.replace(g, clearance=0.0)


# --- bounded oil layers ------------------------------------------------------------------------------
DEPTH = 0.5e-3


@pytest.fixture(scope="module")
def lid_flow(coarse):
    return robot_flow(coarse, MU, H, Domain("lid", DEPTH))


@pytest.fixture(scope="module")
def free_flow(coarse):
    return robot_flow(coarse, MU, H, Domain("free_surface", DEPTH))


def test_no_slip_on_the_lid(lid_flow):
    on_lid = lid_flow._lid_panels()
    idx = np.nonzero(on_lid)[0]
    cen = bem.centroids(lid_flow.tris[idx])
    idx = idx[np.hypot(cen[:, 0], cen[:, 1]) < 3 * DEPTH]
    pts = _on_panels(lid_flow.tris, idx, 5)              # between the lid's collocation points
    u = bem.layer_velocity(pts, lid_flow.tris, lid_flow.density, MU, own=idx)
    assert np.abs(u).max() < 0.01 * np.abs(lid_flow.maps).max()


def test_free_surface_is_flat_and_stress_free(free_flow):
    xs = np.linspace(-1.0e-3, 1.0e-3, 9)
    xx, yy = np.meshgrid(xs, xs)
    top = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, DEPTH)])
    dz = np.array([0.0, 0.0, 2e-6])
    u0 = free_flow.velocity_exact(top)
    up, dn = free_flow.velocity_exact(top + dz), free_flow.velocity_exact(top - dz)
    scale = np.abs(u0[..., :2]).max()
    assert np.abs(u0[..., 2]).max() < 0.01 * scale                     # no flow through the surface
    shear = (up[..., :2] - dn[..., :2]) / (2 * dz[2])                  # ∂u_x/∂z, ∂u_y/∂z
    assert np.abs(shear).max() * DEPTH < 0.01 * scale                  # no shear stress
    assert scale > 1e-4                                                # the surface does move


def test_far_field_of_a_layer_is_a_two_dimensional_dipole(coarse, lid_flow, free_flow):
    # unbounded: Blake's stresslet, u ~ r^-3 at a fixed height (Blake 1971); in a layer the displaced
    # oil returns round the robot, a 2-D potential dipole (Liron & Mochon 1976): u_x ~ r^-2 ahead and
    # a backflow at the side
    unbounded = robot_flow(coarse, MU, H, Domain())
    r = np.array([1.5e-3, 2.5e-3])
    ahead = np.column_stack([r, 0 * r, np.full(2, H)])
    side = np.column_stack([0 * r, r, np.full(2, H)])

    def slope(u):
        return np.log(u[1] / u[0]) / np.log(r[1] / r[0])

    assert slope(unbounded.velocity_exact(ahead)[0][:, 0]) == pytest.approx(-3.0, abs=0.15)
    for f in (lid_flow, free_flow):
        assert slope(f.velocity_exact(ahead)[0][:, 0]) > -2.3
        assert np.all(f.velocity_exact(side)[0][:, 0] < 0)
        assert np.all(unbounded.velocity_exact(side)[0][:, 0] > 0)


@pytest.mark.parametrize("which, tol", [("lid", 1e-4), ("free", 0.01)])
def test_bounded_map_edge_is_continuous(lid_flow, free_flow, which, tol):
    # per unit robot speed; under a free surface the off-map sum carries the glass's images for the
    # sources seen through the surface (the compiled kernel has no others), so only 1 % there
    f = lid_flow if which == "lid" else free_flow
    lim = f.gx[-1]
    v = np.array([[1.0, 0.0]])
    pairs = (([lim * 0.99999, 0.2e-3], [lim * 1.00001, 0.2e-3]), ([0.3e-3, lim * 0.99999], [0.3e-3, lim * 1.00001]))
    for a, b in pairs:
        ua, ub = f.lookup(np.array([a]), v), f.lookup(np.array([b]), v)
        assert np.abs(ua - ub).max() < tol
