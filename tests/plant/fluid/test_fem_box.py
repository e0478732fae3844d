"""The finite-element box model (paper §IV-C): the Stokes solver on exact solutions, the boundary
conditions, and the robot-present pipeline on a coarse mesh."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from magctl.plant.fluid import fem_box
from magctl.plant.fluid.domain import Domain
from magctl.plant.fluid.geometry import RobotGeometry


def _have_fem() -> bool:
    try:
        fem_box.require_fem()
    except ImportError:
        return False
    return True


needs_fem = pytest.mark.skipif(not _have_fem(), reason="the fem extra (scikit-fem, gmsh) is not installed: "
                                                       "pip install 'magctl[fem]'")

MU = 0.019
BOX = Domain("box", 0.5e-3, 1.2e-3, 0.6e-3)      # H, L, W: a small box, coarse meshes only
RNG = np.random.default_rng(7)


def test_missing_extra_is_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "gmsh", None)
    with pytest.raises(fem_box.MissingExtraError, match=r"pip install 'magctl\[fem\]'"):
        fem_box.require_fem()


def test_bad_inputs_are_named():
    g = RobotGeometry.from_params()
    with pytest.raises(fem_box.ParameterError, match="kind 'box'"):
        fem_box.box_mesh(g, Domain())
    with pytest.raises(fem_box.ParameterError, match="outlet"):
        fem_box.box_conditions("x", "open")
    with pytest.raises(fem_box.ParameterError, match="motion"):
        fem_box.box_conditions("z")
    with pytest.raises(fem_box.ParameterError, match="mesh size"):
        fem_box.MeshSpec(-1.0).resolved(g)


# --- exact solutions in the empty box -----------------------------------------------------------
@pytest.fixture(scope="module")
def empty_box():
    return fem_box.box_mesh(RobotGeometry.from_params(), BOX, fem_box.MeshSpec(100e-6, far_size=250e-6),
                            robot=False)


def _inside_points(n=60):
    (x0, x1), (_, w), (_, h) = fem_box._box_bounds(BOX, 0.0)
    return RNG.uniform([x0, 0, 0], [x1, w, h], (n, 3))


@needs_fem
@pytest.mark.parametrize("outlet", ["velocity", "traction"])
def test_plug_flow_is_exact_without_the_robot(empty_box, outlet):
    """The paper's box without the robot: the free stream (−U, 0, 0) everywhere, to round-off (P2 contains it)."""
    bcs, pin = fem_box.box_conditions("x", outlet)
    bcs = [bc for bc in bcs if bc[0] != "body"]
    sol = fem_box.solve_stokes(empty_box, MU, bcs, pin)
    u = sol.velocity(_inside_points())
    assert np.abs(u - [-1.0, 0.0, 0.0]).max() < 1e-10
    assert np.ptp(sol.p) < 1e-8 * MU / 1e-4


@needs_fem
def test_couette_and_poiseuille_are_exact(empty_box):
    """Plane Couette u = U z/H and Poiseuille u = 4 U z (H − z)/H² with dp/dx = −8 μ U/H² are in P2–P1 exactly."""
    h = BOX.depth
    couette = [("z_min", {0: 0.0, 1: 0.0, 2: 0.0}), ("z_max", {0: 1.0, 1: 0.0, 2: 0.0}),
               ("x_min", {0: lambda x: x[2] / h, 1: 0.0, 2: 0.0}), ("x_max", {0: lambda x: x[2] / h, 1: 0.0, 2: 0.0}),
               ("y_min", {1: 0.0}), ("y_max", {1: 0.0})]
    pts = _inside_points()
    sol = fem_box.solve_stokes(empty_box, MU, couette, True)
    assert np.abs(sol.velocity(pts) - np.column_stack([pts[:, 2] / h, 0 * pts[:, :2]])).max() < 1e-10

    def parabola(x):
        return 4 * x[2] * (h - x[2]) / h**2

    poiseuille = [("z_min", {0: 0.0, 1: 0.0, 2: 0.0}), ("z_max", {0: 0.0, 1: 0.0, 2: 0.0}),
                  ("x_min", {0: parabola, 1: 0.0, 2: 0.0}), ("x_max", {0: parabola, 1: 0.0, 2: 0.0}),
                  ("y_min", {1: 0.0}), ("y_max", {1: 0.0})]
    sol = fem_box.solve_stokes(empty_box, MU, poiseuille, True)
    assert np.abs(sol.velocity(pts) - np.column_stack([parabola(pts.T), 0 * pts[:, :2]])).max() < 1e-9
    p = fem_box.evaluate(sol.pbasis, sol.p, np.array([[-0.4e-3, 0.3e-3, 0.2e-3], [0.4e-3, 0.1e-3, 0.4e-3]]))
    assert (p[1] - p[0]) / 0.8e-3 == pytest.approx(-8 * MU / h**2, rel=1e-8)


@needs_fem
def test_translating_sphere_in_a_spherical_container_matches_haberman_sayre():
    """Half model (mirror plane y = 0 as a symmetry face): drag on a sphere of radius a moving at U inside a fixed
    concentric sphere of radius b is 6πμaU·K, K = (1 − λ⁵)/(1 − 9λ/4 + 5λ³/2 − 9λ⁵/4 + λ⁶), λ = a/b
    (Haberman & Sayre 1958; Happel & Brenner 1965 ch. 4; K(1/3) = 2.9754). Within 1.5 % on a coarse mesh
    whose polyhedral spheres carry O(h²) geometry error."""
    skfem, gmsh = fem_box.require_fem()
    a, b, mu = 1.0, 3.0, 1.0
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        shell = occ.cut([(3, occ.addSphere(0, 0, 0, b))], [(3, occ.addSphere(0, 0, 0, a))])[0]
        occ.intersect(shell, [(3, occ.addBox(-b, 0, -b, 2 * b, b, 2 * b))])
        occ.synchronize()
        f = gmsh.model.mesh.field.add("MathEval")
        gmsh.model.mesh.field.setString(f, "F", f"0.3 + 0.5*(Sqrt(x*x+y*y+z*z)-{a})/({b}-{a})")
        gmsh.model.mesh.field.setAsBackgroundMesh(f)
        for opt in ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature"):
            gmsh.option.setNumber(opt, 0)
        gmsh.model.mesh.generate(3)
        mesh = fem_box._gmsh_to_skfem(gmsh, skfem, scale=1.0)
    finally:
        gmsh.finalize()
    bf = mesh.boundary_facets()
    fv = mesh.p[:, mesh.facets[:, bf]]
    r = np.linalg.norm(fv.mean(axis=1), axis=0)
    plane = np.all(np.abs(fv[1]) < 1e-9, axis=0)
    tm = fem_box.TetMesh(mesh, {"y_min": bf[plane], "inner": bf[~plane & (r < 2)], "outer": bf[~plane & (r > 2)]})
    sol = fem_box.solve_stokes(tm, mu, [("y_min", {1: 0.0}), ("outer", {0: 0.0, 1: 0.0, 2: 0.0}),
                                        ("inner", {0: 1.0, 1: 0.0, 2: 0.0})], True)
    lam = a / b
    k = (1 - lam**5) / (1 - 9 / 4 * lam + 5 / 2 * lam**3 - 9 / 4 * lam**5 + lam**6)
    assert k == pytest.approx(2.9754, abs=1e-4)
    drag = 2 * sol.force(tm, "inner")
    assert drag[0] == pytest.approx(-6 * np.pi * mu * a * k, rel=0.015)
    assert abs(drag[2]) < 1e-3 * abs(drag[0])


# --- the robot in the box -----------------------------------------------------------------------
SPEC = fem_box.MeshSpec(100e-6, gap_size=25e-6, far_size=200e-6, grading=0.5)   # ~11k unknowns


@pytest.fixture(scope="module")
def robot_box():
    g = RobotGeometry.from_params()
    mesh = fem_box.box_mesh(g, BOX, SPEC)
    sol, _ = fem_box.box_solve(g, MU, BOX, SPEC, "x", "velocity", mesh=mesh)
    return g, mesh, sol


@needs_fem
def test_mesh_holds_the_same_robot_as_the_geometry(robot_box):
    g, mesh, _ = robot_box
    p = mesh.mesh.p
    verts = np.unique(mesh.mesh.facets[:, mesh.facets["body"]])
    # every robot-surface vertex lies on the solid's surface: inside a slightly grown body, outside a shrunk one
    b = g.to_body(p[:, verts].T)
    from magctl.plant.outline import polygon_distance

    dist, _ = polygon_distance(b[:, :2], g.outline)
    on_face = (np.abs(b[:, 2]) < 1e-9) | (np.abs(b[:, 2] - g.thickness) < 1e-9)
    assert np.all(on_face | (dist < 1e-9))
    assert p[2, verts].min() == pytest.approx(g.clearance, abs=1e-10)
    # no tetrahedron inside the robot
    centroids = p[:, mesh.mesh.t].mean(axis=1).T
    assert not g.contains(centroids).any()


@needs_fem
def test_boundary_conditions_hold_on_robot_and_symmetry_faces(robot_box):
    _, mesh, sol = robot_box
    m = mesh.mesh

    def centroids(name):
        return m.p[:, m.facets[:, mesh.facets[name]]].mean(axis=1).T

    assert np.abs(sol.velocity(centroids("body"))).max() < 1e-12
    assert np.abs(sol.velocity(centroids("y_min"))[:, 1]).max() < 1e-12
    assert np.abs(sol.velocity(centroids("y_max"))[:, 1]).max() < 1e-12
    assert np.abs(sol.velocity(centroids("z_max"))[:, 2]).max() < 1e-12
    assert np.abs(sol.velocity(centroids("z_min")) - [-1.0, 0.0, 0.0]).max() < 1e-12
    # the slip faces do slip: the tangential flow there is not the no-slip zero
    assert np.abs(sol.velocity(centroids("z_max"))[:, 0]).min() > 0.5


@needs_fem
def test_volume_flux_is_conserved_past_the_robot(robot_box):
    """Robot frame: the flux through every cross-section x = c equals the inlet's −U W H (incompressibility)."""
    g, _, sol = robot_box
    w, h = BOX.box_half_width, BOX.depth
    ny, nz = 60, 50
    ys, zs = (np.arange(ny) + 0.5) * w / ny, (np.arange(nz) + 0.5) * h / nz
    for c in (-0.5e-3, -0.1e-3, 0.0, 0.1e-3):
        yy, zz = np.meshgrid(ys, zs)
        pts = np.column_stack([np.full(yy.size, c), yy.ravel(), zz.ravel()])
        u = np.zeros(len(pts))
        fluid = ~g.contains(pts)
        u[fluid] = sol.velocity(pts[fluid])[:, 0]
        assert u.sum() * (w / ny) * (h / nz) == pytest.approx(-w * h, rel=0.01)


@pytest.fixture(scope="module")
def box_flow(tmp_path_factory):
    import os

    old = os.environ.get("MAGCTL_CACHE")
    os.environ["MAGCTL_CACHE"] = str(tmp_path_factory.mktemp("fem_cache"))
    try:
        flow = fem_box.BoxFlow.build(domain=BOX, mesh_size=SPEC, fine_step=30e-6)
        again = fem_box.BoxFlow.build(domain=BOX, mesh_size=SPEC, fine_step=30e-6)
    finally:
        if old is None:
            del os.environ["MAGCTL_CACHE"]
        else:
            os.environ["MAGCTL_CACHE"] = old
    return flow, again


@needs_fem
def test_maps_are_finite_mirror_symmetric_and_zero_outside_the_box(box_flow):
    flow, _ = box_flow
    m = flow.maps
    assert m.shape == (2, len(flow.gy), len(flow.gx), 3) and np.isfinite(m).all()
    np.testing.assert_array_equal(flow.gx, -flow.gx[::-1])
    # body-x motion: u_x, u_z even in y and u_y odd; body-y motion the reverse
    np.testing.assert_allclose(m[:, ::-1], m * np.array([[1, -1, 1], [-1, 1, -1]])[:, None, None, :], atol=1e-12)
    # rigid motion inside the robot, zero on and beyond the box's ends
    assert flow.inside.any()
    np.testing.assert_allclose(m[0][flow.inside], [[1.0, 0.0, 0.0]] * int(flow.inside.sum()))
    np.testing.assert_allclose(m[1][flow.inside], [[0.0, 1.0, 0.0]] * int(flow.inside.sum()))
    assert np.all(m[:, :, [0, -1]] == 0) and np.all(m[:, [0, -1]] == 0)
    assert np.all(flow.lookup(np.array([[2e-3, 0.0], [0.0, -2e-3]]), np.array([1.0, 1.0])) == 0)
    # the front of the robot pushes oil forward along its path, beside it the flow follows the motion
    jx = np.searchsorted(flow.gx, 0.25e-3)
    assert m[0, len(flow.gy) // 2, jx, 0] > 0.1
    # drag opposes the motion
    d = flow.drag()
    assert d[0, 0] < 0 and d[1, 1] < 0


@needs_fem
def test_maps_are_cached_by_every_input(box_flow):
    flow, again = box_flow
    assert not flow.info["cached"] and again.info["cached"]
    np.testing.assert_array_equal(flow.maps, again.maps)
    g = RobotGeometry.from_params()
    base = dict(geometry=g, viscosity=MU, height=105e-6, domain=BOX, gx=flow.gx, gy=flow.gy, spec=SPEC,
                robot_x=0.0, outlet="velocity")
    changes = [{}, {"robot_x": 1e-5}, {"outlet": "traction"}, {"height": 110e-6}, {"spec": fem_box.MeshSpec(70e-6)},
               {"viscosity": 2 * MU}, {"domain": Domain("box", 0.5e-3, 1.2e-3, 0.7e-3)}, {"gx": flow.gx * 1.01},
               {"geometry": RobotGeometry(g.outline, g.thickness, 0.3, clearance=g.clearance)}]
    keys = {fem_box.map_key(**{**base, **c}) for c in changes}
    assert len(keys) == len(changes)


@needs_fem
def test_spheres_run_the_side_pass_with_the_box_flow(box_flow, monkeypatch):
    from reference import reference_of

    from magctl.core.errors import ParameterError
    from magctl.plant.fluid import scenarios
    from magctl.plant.fluid.scenarios import sidepush_curve
    from magctl.plant.sphere import Spheres

    flow, _ = box_flow
    gaps = np.array([400e-6, 550e-6])
    res = sidepush_curve(gaps, travel=0.5e-3, flow=flow)
    assert np.isfinite(res.displacement).all() and not res.contact.any() and np.all(res.displacement > 0)
    # the block's kernel against the numpy array form (tests/reference) on the same box flow
    monkeypatch.setattr(scenarios, "_spheres", lambda initial, **kw: reference_of(Spheres(initial, **kw)))
    arrays = sidepush_curve(gaps, travel=0.5e-3, flow=flow)
    monkeypatch.undo()
    np.testing.assert_allclose(arrays.displacement, res.displacement, rtol=1e-6)
    other = RobotGeometry(flow.geometry.outline * 0.9, flow.geometry.thickness, flow.geometry.tilt)
    with pytest.raises(ParameterError, match="another robot geometry"):
        Spheres(np.zeros((1, 2)), geometry=other, flow=flow)
