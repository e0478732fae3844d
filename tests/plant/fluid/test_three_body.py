"""The pieces of the robot–sphere–glass solve against exact Stokes solutions.

* two equal spheres along their line of centres: Stimson & Jeffery's (1926) and Maude's (1961) exact
  series (:mod:`magctl.plant.fluid.bispherical`), themselves checked against the method of reflections far
  apart and Jeffrey & Onishi's (1984) lubrication form near contact; the boundary elements of
  :mod:`magctl.plant.fluid.three_body` against both series;
* a lone sphere above the glass: the full 3 × 3 resistance (translation, normal motion, rotation and
  their coupling) the wall-gap splitting uses, against the same boundary elements;
* the study's inverse of the film law against the plant's film.
"""

import numpy as np
import pytest

from magctl.plant.fluid import bem
from magctl.plant.fluid.bispherical import two_spheres_approach, two_spheres_together
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.lubrication import edge_curvatures, film_area
from magctl.plant.fluid.three_body import (
    Mesh,
    nearest_edge,
    notch_front,
    predict,
    refine,
    solve_response,
    sphere_half,
    wall_resistance,
)


def test_pair_series_match_reflections_far_and_lubrication_near():
    for gap in (60.0, 200.0):
        d = 2.0 + gap                                  # centre distance in radii
        # method of reflections to O(d⁻³) (Happel & Brenner 1965, ch. 6): 1 ∓ 3/2d + 9/4d² ∓ 19/8d³
        assert two_spheres_together(gap) == pytest.approx(1 - 1.5 / d + 2.25 / d**2 - 2.375 / d**3, abs=10 / d**4)
        assert two_spheres_approach(gap) == pytest.approx(1 + 1.5 / d + 2.25 / d**2 + 2.375 / d**3, abs=10 / d**4)
    # near contact: a/2δ + (9/20) ln(a/δ) + a constant — the remainder settles as δ → 0
    rest = [two_spheres_approach(g) - (0.5 / g + 0.45 * np.log(1 / g)) for g in (1e-3, 1e-4, 1e-5)]
    assert abs(rest[1] - rest[2]) < 0.1 * abs(rest[0] - rest[1]) + 1e-4
    # Stimson & Jeffery (1926): λ = 0.645 for two spheres in contact moving together
    assert two_spheres_together(1e-6) == pytest.approx(0.645, abs=1e-3)


def _pair_forces(gap: float, height: float = 500.0):
    """F/(6πμaU) on sphere 1 (unit radius, at x = −1 − gap/2) for both spheres moving +x, and for sphere 1
    at +x and sphere 2 at −x (approach), both far above the glass."""
    c1, c2 = np.array([-1 - gap / 2, 0, height]), np.array([1 + gap / 2, 0, height])

    def size(other):
        return lambda p: np.clip(0.4 * (np.linalg.norm(p - other, axis=1) - 1.0), 0.01, 0.25)

    s1, s2 = sphere_half(c1, 1.0, size(c2)), sphere_half(c2, 1.0, size(c1))
    even, _ = bem.y_symmetric(np.concatenate([s1, s2]), np.r_[np.zeros(len(s1), int), np.ones(len(s2), int)])
    n1 = len(s1)
    rhs = np.zeros((2, even.n_independent, 3))
    rhs[:, :, 0] = 1.0
    rhs[1, n1:, 0] = -1.0
    q = bem.solve(even, rhs, 1.0, deflate=True)
    own = np.r_[np.ones(n1, bool), np.zeros(len(s2), bool)]
    own = np.concatenate([own, own])
    return (q[:, own, 0] * bem.areas(even.tris[own])).sum(axis=1) / (6 * np.pi)


@pytest.mark.parametrize("gap", [0.5, 0.2])
def test_boundary_elements_give_two_spheres_exactly(gap):
    together, approach = _pair_forces(gap)
    assert together == pytest.approx(two_spheres_together(gap), rel=0.01)
    assert approach == pytest.approx(two_spheres_approach(gap), rel=0.015)


def test_lone_sphere_wall_resistance_matches_boundary_elements():
    """Signs and sizes of every entry the wall-gap splitting adds, rotation coupling included."""
    centre = np.array([0.0, 0.0, 1.2])
    half = sphere_half(centre, 1.0, lambda p: np.clip(0.5 * p[:, 2], 0.015, 0.25))
    even, _ = bem.y_symmetric(half)
    n = even.n_independent
    rel = bem.centroids(even.tris[:n]) - centre
    rhs = np.zeros((3, n, 3))
    rhs[0, :, 0], rhs[1, :, 2] = 1.0, 1.0
    rhs[2, :, 0], rhs[2, :, 2] = rel[:, 2], -rel[:, 0]
    f = bem.solve(even, rhs, 1.0, deflate=True) * bem.areas(even.tris)[None, :, None]
    r = bem.centroids(even.tris) - centre
    torque = (r[None, :, 2] * f[..., 0] - r[None, :, 0] * f[..., 2]).sum(axis=1)
    load = np.column_stack([f.sum(axis=1)[:, 0], f.sum(axis=1)[:, 2], torque]).T
    exact = wall_resistance(1.0, 0.2, 1.0)
    assert np.sign(exact[0, 2]) == np.sign(load[0, 2]) == np.sign(load[2, 0])
    np.testing.assert_allclose(load, exact, rtol=0.02, atol=0.02 * np.abs(exact).max())


def test_sphere_mesh_lies_on_the_sphere_and_obeys_its_size_field():
    centre = np.array([2.0, 0.0, 1.5])
    tris = sphere_half(centre, 1.0, lambda p: np.clip(0.3 * p[:, 2], 0.05, 0.3))
    assert np.allclose(np.linalg.norm(tris - centre, axis=2), 1.0)
    assert tris[..., 1].min() >= 0.0
    assert bem.areas(tris).sum() == pytest.approx(2 * np.pi, rel=0.01)
    flat = refine(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]]), lambda p: np.full(len(p), 0.1))
    assert bem.areas(flat).sum() == pytest.approx(0.5) and np.allclose(flat[..., 2], 0.0)


def test_the_studys_resistance_inverse_recovers_the_plants_laws():
    """needed_resistance inverts predict's steady relation: from the plant's speeds it returns the resistance of
    the law the plant gives the notch (the edge law) and of the face film, each computed from the laws' formulas."""
    from magctl.plant.fluid.params import sphere_params
    from magctl.plant.fluid.three_body import needed_resistance
    from magctl.plant.fluid.wall_drag import accurate_coefficients

    g = RobotGeometry.from_params()
    p = sphere_params()
    a, eps = p.radius, p.roughness
    centre = np.array([notch_front(g) + 1.1 * a, 0.0, a + eps])
    pred = predict(g, centre, a, 0.6, p)
    f_t, f_r, t_t, t_r, _, _ = accurate_coefficients(eps / a)
    zeta = abs((f_t * t_r - f_r * t_t) / t_r)
    h = pred.gap_footprint / a
    edge_law = p.edge_coefficient * np.log(p.edge_cutoff / h)
    _, edge = nearest_edge(centre[:2], g.footprint)
    face = film_area(a, edge_curvatures(g.footprint))[edge] / a**2 * (1 / h - 1 / p.film_cutoff)
    assert needed_resistance(pred.with_film, pred.one_way, zeta) == pytest.approx(edge_law, rel=1e-9)
    assert needed_resistance(pred.face_film, pred.one_way, zeta) == pytest.approx(face, rel=1e-9)
    assert pred.one_way < pred.with_film < pred.face_film < 1


def test_bad_configurations_are_refused():
    g = RobotGeometry.from_params()
    with pytest.raises(ValueError, match="y = 0"):
        solve_response(g, [3e-4, 1e-5, 1.2e-4], 105e-6, 0.019, Mesh())
    with pytest.raises(ValueError, match="overlaps"):
        solve_response(g, [0.0, 0.0, 1.2e-4], 105e-6, 0.019, Mesh())


def test_the_plants_edge_law_is_the_fit_to_the_committed_three_body_results():
    """models/sphere.toml's edge law (C, h_e) is fit_edge_law over the resistances the three-body study needed
    (docs/three-body-results.md, written by `magctl study three-body`): refitted from that table here."""
    from pathlib import Path

    from magctl.plant.fluid.lubrication import fit_edge_law
    from magctl.plant.fluid.params import sphere_params

    text = (Path(__file__).parents[3] / "docs" / "three-body-results.md").read_text()
    rows = [line.split("|")[1:-1] for line in text.splitlines() if line.startswith("| ") and line.count("|") == 10]
    rows = [r for r in rows if r[0].strip()[0].isdigit()]
    assert len(rows) >= 4
    p = sphere_params()
    gaps = np.array([float(r[0]) for r in rows]) * 1e-6 / p.radius
    needed = np.array([float(r[7]) for r in rows])
    c, h_e, residual = fit_edge_law(gaps, needed)
    assert p.edge_coefficient == pytest.approx(c, rel=5e-3) and p.edge_cutoff == pytest.approx(h_e, rel=5e-3)
    assert residual < 0.1
