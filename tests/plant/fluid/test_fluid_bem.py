"""The boundary-element solver against exact Stokes solutions for a sphere near the wall.

* normal translation: Brenner (1961), exact bipolar-coordinate series, computed here;
* parallel translation (non-rotating sphere): O'Neill (1964), as tabulated by Goldman, Cox &
  Brenner (1967a): h/a = 10.0677, 3.7622, 2.3524 → F/(6πμaU) = 1.0591, 1.1738, 1.3079.

Meshes: an octahedral sphere (no panel crosses y = 0, so the y-mirror halves the system),
refined towards the glass (edge ≤ max(β·height, h_min)) and capped at an edge h_max.
"""

import functools

import numpy as np
import pytest

from magctl.plant.fluid import bem
from magctl.plant.fluid.three_body import octahedron_half


def _split(t, radius=1.0):
    m01, m12, m20 = t[:, 0] + t[:, 1], t[:, 1] + t[:, 2], t[:, 2] + t[:, 0]
    m01, m12, m20 = (radius * m / np.linalg.norm(m, axis=1, keepdims=True) for m in (m01, m12, m20))
    return np.concatenate([np.stack([t[:, 0], m01, m20], 1), np.stack([m01, t[:, 1], m12], 1),
                           np.stack([m20, m12, t[:, 2]], 1), np.stack([m01, m12, m20], 1)])


def sphere_half(centre_height, h_max, beta, h_min, radius=1.0):
    """y > 0 half of a sphere of ``radius`` centred at ``(0, 0, centre_height)``, graded to the glass."""
    t = octahedron_half() * radius
    for _ in range(12):
        edge = np.linalg.norm(t[:, 1] - t[:, 0], axis=1)
        height = t[..., 2].min(axis=1) + centre_height
        ref = edge > np.minimum(h_max, np.maximum(beta * height, h_min))
        if not ref.any():
            break
        t = np.concatenate([t[~ref], _split(t[ref], radius)])
    t[..., 2] += centre_height
    return t


@functools.cache
def sphere_drag(centre_height, mesh):
    """F/(6πμaU) of a unit sphere translating along x (non-rotating) and along z."""
    even, _ = bem.y_symmetric(sphere_half(centre_height, *mesh))
    n = even.n_independent
    rhs = np.zeros((2, n, 3))
    rhs[0, :, 0] = 1.0
    rhs[1, :, 2] = 1.0
    q = bem.solve(even, rhs, 1.0, deflate=True)
    force = (q * bem.areas(even.tris)[None, :, None]).sum(axis=1) / (6 * np.pi)
    return force[0, 0], force[1, 2], 2 * n


def brenner_normal(h_over_a):
    """Brenner (1961) eq 2.19: λ = (4/3) sinh α Σ n(n+1)/((2n−1)(2n+3)) [(2 sinh(2n+1)α + (2n+1) sinh 2α)
    / (4 sinh²(n+½)α − (2n+1)² sinh² α) − 1], cosh α = h/a."""
    al = np.arccosh(h_over_a)
    n = np.arange(1, int(min(400, 300 / al)))
    num = 2 * np.sinh((2 * n + 1) * al) + (2 * n + 1) * np.sinh(2 * al)
    den = 4 * np.sinh((n + 0.5) * al) ** 2 - (2 * n + 1) ** 2 * np.sinh(al) ** 2
    return 4 / 3 * np.sinh(al) * np.sum(n * (n + 1) / ((2 * n - 1) * (2 * n + 3)) * (num / den - 1))


def test_brenner_series_reproduces_his_table():
    # Brenner (1961) Table 1: alpha = 1.0 (h/a = 1.5431) -> 3.0361, alpha = 3.0 (h/a = 10.0677) -> 1.1253
    assert brenner_normal(np.cosh(1.0)) == pytest.approx(3.0361, abs=2e-4)
    assert brenner_normal(np.cosh(3.0)) == pytest.approx(1.1253, abs=2e-4)


FINE = (0.2, 0.25, 0.02)
ONEILL = [(10.0677, 1.0591), (3.7622, 1.1738), (2.3524, 1.3079)]


@pytest.mark.slow
@pytest.mark.parametrize("h_over_a, f_parallel", ONEILL)
def test_sphere_far_from_wall_matches_oneill_and_brenner(h_over_a, f_parallel):
    fp, fn, _ = sphere_drag(h_over_a, FINE)
    assert fp == pytest.approx(f_parallel, rel=0.01)
    assert fn == pytest.approx(brenner_normal(h_over_a), rel=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("gap", [1.0, 0.5, 0.2, 0.1])
def test_sphere_approaching_the_wall_matches_brenner(gap):
    _, fn, _ = sphere_drag(1.0 + gap, FINE)
    assert fn == pytest.approx(brenner_normal(1.0 + gap), rel=0.01)


@pytest.mark.slow
def test_convergence_is_second_order_at_a_small_gap():
    # error ~ (panel size)^2 ~ 1/panels: halving h cuts it about four-fold
    exact = brenner_normal(1.1)
    errs, counts = [], []
    for scale in (2.0, 1.41421356, 1.0):
        mesh = FINE if scale == 1.0 else tuple(v * scale for v in FINE)
        _, fn, n = sphere_drag(1.1, mesh)
        errs.append(abs(fn / exact - 1))
        counts.append(n)
    order = -np.polyfit(np.log(counts), np.log(errs), 1)[0]      # error ~ N^-order, N ~ h^-2
    assert errs[0] > errs[1] > errs[2]
    assert 0.7 < order < 1.5
    assert errs[2] < 0.01


def test_bad_input():
    with pytest.raises(ValueError, match="above the glass"):
        bem.single_layer(np.zeros((1, 3)), np.array([[[0, 0, 0.0], [1, 0, 1], [0, 1, 1]]]))
    with pytest.raises(ValueError, match="triangles"):
        bem.single_layer(np.zeros((1, 3)), np.ones((2, 3)))
    even, _ = bem.y_symmetric(sphere_half(2.0, 1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="boundary velocity"):
        bem.solve(even, np.zeros((1, 3, 3)), 1.0, deflate=True)


def faxen_midway(lam):
    """Faxén (1923) via Happel & Brenner (1965) eq 7-4.28: a sphere midway between two walls, λ = a/l
    (l the distance to each wall): F/(6πμaU) = 1/(1 − 1.004λ + 0.418λ³ + 0.21λ⁴ − 0.169λ⁵)."""
    return 1.0 / (1 - 1.004 * lam + 0.418 * lam**3 + 0.21 * lam**4 - 0.169 * lam**5)


@pytest.mark.slow
@pytest.mark.parametrize("half_gap", [5.0, 3.0])
def test_sphere_midway_between_glass_and_lid_matches_faxen(half_gap):
    from magctl.plant.fluid.flow import LID_PANELS, LID_RADIUS, lid_half

    top = 2 * half_gap
    sphere = sphere_half(half_gap, 0.2, 1.0, 0.2)
    lid = lid_half(top, LID_RADIUS * top, LID_PANELS * top, top)
    body = np.concatenate([np.zeros(len(sphere), int), np.full(len(lid), -1)])
    even, _ = bem.y_symmetric(np.concatenate([sphere, lid]), body)
    rhs = np.zeros((1, even.n_independent, 3))
    rhs[0, :len(sphere), 0] = 1.0
    q = bem.solve(even, rhs, 1.0, deflate=True)[0]
    on_sphere = np.concatenate([body, body]) == 0
    force = (q * bem.areas(even.tris)[:, None])[on_sphere].sum(axis=0) / (6 * np.pi)
    assert force[0] == pytest.approx(faxen_midway(1 / half_gap), rel=0.01)
