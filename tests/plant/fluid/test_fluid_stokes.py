"""Blake's wall Stokeslet and the point-force sums of the far field against closed forms."""

import numpy as np
import pytest

from magctl.plant.fluid.stokes import (
    blake_tensor,
    blake_velocity,
    regularized_blake_velocity,
)

RNG = np.random.default_rng(4)


def free_stokeslet(x, y, f, mu):
    r = x - y
    n = np.linalg.norm(r, axis=-1, keepdims=True)
    return (f / n + r * (r @ f)[:, None] / n**3) / (8 * np.pi * mu)


def test_flow_vanishes_on_the_wall():
    y = RNG.random((7, 3)) + [0, 0, 0.05]
    x = RNG.random((40, 3)) * 6 - 3
    x[:, 2] = 0.0
    f = RNG.standard_normal((7, 3))
    assert np.abs(blake_velocity(x, y, f, 1.0)).max() < 1e-14


@pytest.mark.parametrize("axis, coeff", [(0, 3 / 32), (2, 3 / 16)])
def test_image_flow_at_the_force_is_lorentz_reflection(axis, coeff):
    # the wall's image flow at the point force: -(3/32) F/(pi mu h) parallel, -(3/16) F/(pi mu h) normal
    # (Lorentz 1907; the a/h term of Faxen's mobility 1 - 9/16 a/h and Brenner's 1 - 9/8 a/h)
    h, mu = 1.7, 0.3
    y = np.array([[0.2, -0.4, h]])
    x = y + [[0, 0, 1e-6]]
    f = np.zeros((1, 3))
    f[0, axis] = 1.0
    image = blake_velocity(x, y, f, mu)[0] - free_stokeslet(x, y[0], f[0], mu)[0]
    assert image[axis] == pytest.approx(-coeff / (np.pi * mu * h), rel=1e-4)


def test_reciprocity():
    # Lorentz reciprocal theorem: G_ij(x, y) = G_ji(y, x) for points in the fluid
    x = RNG.random((5, 3)) + [0, 0, 0.1]
    y = RNG.random((6, 3)) + [0, 0, 0.1]
    g_xy = blake_tensor(x, y)
    g_yx = blake_tensor(y, x)
    assert np.allclose(g_xy, np.transpose(g_yx, (2, 3, 0, 1)), rtol=1e-10, atol=1e-12)


def test_far_field_is_blakes_stresslet():
    # Blake 1971 eq 21: far along the wall a parallel Stokeslet at height h gives
    # u_i = 12 h z x_i x_j F_j / (8 pi mu rho^5)  (decay rho^-3 at fixed z)
    h, z, mu = 1.0, 0.7, 0.4
    y = np.array([[0.0, 0.0, h]])
    f = np.array([[1.0, 0.0, 0.0]])
    for rho in (300.0, 600.0):
        x = np.array([[rho * 0.6, rho * 0.8, z]])
        u = blake_velocity(x, y, f, mu)[0]
        xa = x[0, :2]
        expected = 12 * h * z * xa * xa[0] / (8 * np.pi * mu * rho**5)
        assert u[:2] == pytest.approx(expected, rel=5e-3)


def test_normal_stokeslet_decays_faster():
    # a wall-normal Stokeslet has no stresslet far field: it decays as rho^-4 (Blake 1971)
    y = np.array([[0.0, 0.0, 1.0]])
    f = np.array([[0.0, 0.0, 1.0]])
    x = np.array([[200.0, 0.0, 1.0], [400.0, 0.0, 1.0]])
    u = np.linalg.norm(blake_velocity(x, y, f, 1.0), axis=1)
    assert np.log(u[1] / u[0]) / np.log(2.0) == pytest.approx(-4.0, abs=0.01)


def test_divergence_free():
    y = np.array([[0.1, 0.2, 0.8]])
    f = np.array([[0.3, -1.0, 0.7]])
    x0 = np.array([0.9, -0.4, 0.6])
    h = 1e-4
    div = 0.0
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        up = blake_velocity((x0 + e)[None], y, f, 1.0)[0, i]
        um = blake_velocity((x0 - e)[None], y, f, 1.0)[0, i]
        div += (up - um) / (2 * h)
    assert abs(div) < 1e-7


def test_point_force_sum_is_blakes_tensor_and_regularisation_vanishes_far_away():
    """The far-field sum the flow look-up uses (eps = 0) is Blake's tensor applied to the forces, and a
    regularisation blob changes the flow only at O((eps/r)^2) far from the forces."""
    y = RNG.random((20, 3)) + [0, 0, 0.2]
    f = RNG.standard_normal((2, 20, 3))
    near = RNG.random((25, 3)) + [2.0, 0.0, 0.0]
    exact = np.einsum("pimj,kmj->kpi", blake_tensor(near, y), f) / (8 * np.pi * 2.0)
    assert np.allclose(regularized_blake_velocity(near, y, f, 2.0, 0.0), exact, rtol=1e-12, atol=1e-14)
    far = RNG.random((30, 3)) * 10 + [20, 0, 0]
    u_sing = regularized_blake_velocity(far, y, f, 1.0, 0.0)
    u_reg = regularized_blake_velocity(far, y, f, 1.0, 0.01)
    assert np.abs(u_sing - u_reg).max() < 1e-4 * np.abs(u_sing).max()
