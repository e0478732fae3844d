"""Robot–sphere lubrication (magctl.plant.fluid.lubrication) against exact solutions: Brenner's (1961)
series for a sphere approaching a plane, a finite-difference solution of the Reynolds equation for a
non-axisymmetric gap, the circle a polygon arc was drawn from, the tilted body's own faces, and the
gap's ODE integrated by scipy."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.integrate import solve_ivp
from scipy.sparse.linalg import spsolve

from magctl.config import load_model
from magctl.core.errors import ParameterError
from magctl.plant.fluid.bispherical import normal_translation
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.lubrication import (
    edge_curvatures,
    face_heights,
    film_area,
    film_gap,
    film_laws,
    film_resistance,
    fit_edge_law,
)
from magctl.plant.outline import star_outline
from magctl.plant.sphere import Spheres

A = 105e-6


@pytest.mark.parametrize("gap_ratio", [1e-3, 3e-3, 1e-2])
def test_flat_face_film_is_brenners_leading_term(gap_ratio):
    """A flat face (curvature 0) gives A = a², so the film's 6πμA/h is Brenner's exact normal drag
    6πμaλ to its leading order: λ h/a → 1 with the error of the next terms, (−ln(h/a)/5 + 0.97) h/a."""
    lam = normal_translation(gap_ratio)
    film = film_area(A, 0.0) / A**2 / gap_ratio
    assert film_area(A, 0.0) == pytest.approx(A**2, rel=1e-14)
    assert lam / film - 1 == pytest.approx((-0.2 * np.log(gap_ratio) + 0.971264) * gap_ratio, rel=0.05)


def _reynolds_force(rx: float, rz: float, h0: float, n: int = 401, half_width: float = 30.0) -> float:
    """Squeeze force of the gap h0 + x²/2rx + z²/2rz closing at unit speed in unit viscosity:
    ∇·(h³∇p) = 12 on a grid (scaled x = √(2 rx h0) X), p = 0 on the edges, conservative differences."""
    s = np.linspace(-half_width, half_width, n)
    d = s[1] - s[0]
    lx, lz = np.sqrt(2 * rx * h0), np.sqrt(2 * rz * h0)
    X, Z = np.meshgrid(s, s, indexing="ij")
    h3 = lambda x, z: (h0 * (1 + x**2 + z**2)) ** 3  # noqa: E731
    idx = np.arange(n * n).reshape(n, n)
    rows, cols, vals = [], [], []
    inner = idx[1:-1, 1:-1].ravel()
    xi, zi = X[1:-1, 1:-1].ravel(), Z[1:-1, 1:-1].ravel()
    diag = np.zeros(inner.size)
    for (di, dj), (hx, scale) in {(1, 0): ((d / 2, 0), lx), (-1, 0): ((-d / 2, 0), lx),
                                  (0, 1): ((0, d / 2), lz), (0, -1): ((0, -d / 2), lz)}.items():
        w = h3(xi + hx[0] if di else xi, zi + hx[1] if dj else zi) / (d * scale) ** 2
        ii, jj = np.unravel_index(inner, (n, n))
        nb = idx[ii + di, jj + dj]
        rows.append(inner)
        cols.append(nb)
        vals.append(w)
        diag -= w
    rows.append(inner)
    cols.append(inner)
    vals.append(diag)
    edge = np.setdiff1d(idx.ravel(), inner)
    rows.append(edge)
    cols.append(edge)
    vals.append(np.ones(edge.size))
    mat = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * n, n * n))
    rhs = np.zeros(n * n)
    rhs[inner] = 12.0
    p = spsolve(mat.tocsc(), rhs)
    return -p.sum() * d * d * lx * lz


def test_film_area_matches_the_reynolds_equation_for_an_elliptic_gap():
    """A = 2 (R_x R_z)^{3/2}/(R_x + R_z) is exact for the paraboloidal gap: a finite-difference solution
    of the Reynolds equation agrees within the truncation of its finite domain (1 %), also for the
    concave front notch's 4:1 gap, and the axisymmetric case is 6πR²/h."""
    h0 = 1e-6
    for rx, rz in ((A, A), (4 * A, A)):
        exact = 6 * np.pi * 2 * (rx * rz) ** 1.5 / (rx + rz) / h0
        assert _reynolds_force(rx, rz, h0) == pytest.approx(exact, rel=0.01)
    notch = 1.0 / A - 1.0 / (4 * A)                        # the curvature that makes R_x = 4a
    assert film_area(A, notch) == pytest.approx(2 * (4 * A * A) ** 1.5 / (5 * A), rel=1e-12)
    assert film_area(A, -1.0 / A) < film_area(A, 0.0) < film_area(A, 0.5 / A)   # convex < flat < concave


def test_edge_curvatures_recover_the_arc_radius():
    """A circle drawn counter-clockwise is convex everywhere (−1/ρ); the star's concave front notch gives +1/ρ
    on its inner edges, ρ = (c²/4 + d²)/2d from its chord c and depth d (models/robot_geometry.toml)."""
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    circle = 200e-6 * np.column_stack([np.cos(t), np.sin(t)])
    np.testing.assert_allclose(edge_curvatures(circle), -1 / 200e-6, rtol=1e-12)
    g = load_model("robot_geometry").outline
    c, d = g.front_notch_width, g.front_notch_depth
    outline = star_outline(g.length, g.width, d, c, 0.0, 0.0, 9)
    rho = (c**2 / 4 + d**2) / (2 * d)
    notch = edge_curvatures(outline)[2:8]                  # the inner edges of the 9-point front arc
    np.testing.assert_allclose(notch, 1 / rho, rtol=1e-9)


def test_face_heights_are_where_the_sphere_meets_each_face_of_the_tilted_body():
    """For every footprint edge, the face is built in 3-D from its corners (geometry.to_frame): the point
    ``face_heights`` up the face from the edge's middle, with a sphere of radius a touching the face's plane
    there from outside, has the sphere's centre at height a (resting on the glass). The front notch meets the
    sphere below its bottom rim, the rear above its top rim, the flanks on the face."""
    g = RobotGeometry.from_params()
    a = 105e-6
    heights = face_heights(g, a)
    o = g.outline
    for k in range(len(o)):
        p, q = o[k], o[(k + 1) % len(o)]
        corners = g.to_frame(np.array([[*p, 0.0], [*q, 0.0], [*p, g.thickness]]))
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])   # outward: counter-clockwise outline
        normal /= np.linalg.norm(normal)
        up = (corners[2] - corners[0]) / g.thickness
        contact = g.to_frame(np.array([*(p + q) / 2, 0.0])) + heights[k] * up
        centre = contact + a * normal
        assert centre[2] == pytest.approx(a, abs=1e-12)
        assert (centre - corners[0]) @ normal == pytest.approx(a, abs=1e-12)
    front, rear = np.argmax(o[:, 0] + np.roll(o[:, 0], -1)), np.argmin(o[:, 0] + np.roll(o[:, 0], -1))
    assert heights[front] < 0 < g.thickness < heights[rear]
    area, log_coef = film_laws(g, a, 3.0)
    assert log_coef[front] == log_coef[rear] == pytest.approx(3 * a) and area[front] == area[rear] == 0
    flank = np.argmax(o[:, 1] + np.roll(o[:, 1], -1))
    assert area[flank] > 0 and log_coef[flank] == 0


def test_edge_law_fit_recovers_a_log_law_and_refuses_bad_data():
    h = np.geomspace(0.02, 0.5, 6)
    c, h_e, residual = fit_edge_law(h, 2.7 * np.log(0.8 / h))
    assert (c, h_e, residual) == pytest.approx((2.7, 0.8, 0.0), abs=1e-10)
    with pytest.raises(ParameterError, match="positive"):
        fit_edge_law([0.1, -0.2], [1.0, 2.0])


LAWS = [(3e-6, 105e-6, 0.0, 77e-6), (0.0, 105e-6, 250e-6, 77e-6), (1e-6, 30e-6, 100e-6, 60e-6)]


@pytest.mark.parametrize("law", LAWS)
@pytest.mark.parametrize("s", [-30e-6, -1e-6, 0.0, 2e-6, 80e-6])
def test_film_gap_integrates_the_gap_ode(s, law):
    """film_gap is the exact sub-step of dh/dt = w/(1 + R(h)/ζ) for the face film, the edge law and both, across
    their cut-offs: against scipy's integration of that ODE, stopped at h_min where the gap closes."""
    k_face, h_face, k_edge, h_edge = law
    h0, tau, h_min = 2e-6, 1.0, 25e-9
    w = s / tau
    rate = lambda t, h: [w / (1 + float(film_resistance(max(h[0], 1e-12), k_face, k_edge, h_face, h_edge)))]  # noqa: E731
    closes = lambda t, h: h[0] - h_min  # noqa: E731
    closes.terminal = True
    ode = solve_ivp(rate, (0, tau), [h0], rtol=1e-11, atol=1e-16, events=closes)
    expected = h_min if ode.status == 1 else ode.y[0, -1]
    assert film_gap(h0, s, k_face, h_face, k_edge, h_edge, h_min) == pytest.approx(expected, rel=1e-7)


def test_edge_law_keeps_the_release_finite_as_the_contact_gap_closes():
    """Backing away from a sphere in its notch: with the notch's face film (6πμA/h) the sphere follows the
    robot further the closer the contact, by the film's ln h₀; with the edge law the plant uses there
    (6πμaC ln(h_e/h), whose integral is finite at h → 0) the contact gap hardly matters. Without either
    (the paper's drag mode: one-way flow) the release is the same for every contact gap."""
    from magctl.plant.fluid.scenarios import release_displacement

    gaps = (0.3e-6, 10e-6)
    edge = [release_displacement(contact_gap=h)[0] for h in gaps]
    face = [release_displacement(contact_gap=h, lubrication="face")[0] for h in gaps]
    assert face[0] - face[1] > 100e-6
    assert abs(edge[0] - edge[1]) < 0.2 * (face[0] - face[1])
    paper = [release_displacement(contact_gap=h, drag_mode="paper")[0] for h in gaps]
    assert paper[0] == pytest.approx(paper[1], rel=1e-12)
    block = Spheres(np.zeros((1, 2)))
    assert block.film_cutoff == pytest.approx(block.radius) and block.contact_gap == pytest.approx(25e-9)
