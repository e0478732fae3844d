"""Stokes flow above a no-slip plane wall: Blake's image system.

The fundamental solution is the Stokeslet above a plane wall (Blake 1971), which
satisfies no-slip on ``z = 0`` exactly. It is the Green's function of the
boundary-element robot flow (:mod:`magctl.plant.fluid.bem`) and, summed over
point forces, the flow far from the robot (:mod:`magctl.plant.fluid.flow`).

References
----------
Blake, J. R. (1971). A note on the image system for a stokeslet in a no-slip
boundary. Proc. Camb. Phil. Soc. 70, 303-310.
"""

from __future__ import annotations

import numpy as np

_M = np.array([1.0, 1.0, -1.0])  # the image reflection, diag(1, 1, -1)


def blake_tensor(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Blake's Green's tensor ``G_ij(x, y)`` for a point force at ``y`` above the wall ``z = 0``.

    The velocity at ``x`` due to a force ``f`` (on the fluid) at ``y`` is
    ``u_i = G_ij f_j / (8 π μ)``, with (Blake 1971, eq 14)

    ``G_ij = S_ij(r) - S_ij(R) + 2 h m_j D_ij``,
    ``S_ij(r) = δ_ij/|r| + r_i r_j/|r|³``,
    ``D_ij = ∂/∂R_j [h R_i/|R|³ - δ_i3/|R| - R_i R_3/|R|³]``, ``m = (1, 1, -1)``,

    where ``h`` is the force's height, ``r = x - y`` and ``R = x - y*`` with the mirror point
    ``y* = (y1, y2, -h)``.

    Parameters
    ----------
    x : ndarray, shape (P, 3)
        Field points [m], ``z >= 0``.
    y : ndarray, shape (M, 3)
        Force points [m], ``z > 0``.

    Returns
    -------
    ndarray, shape (P, 3, M, 3)
        ``G[p, i, m, j]`` [1/m].
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    if np.any(y[:, 2] <= 0):
        raise ValueError("Stokeslets must lie above the wall (z > 0)")
    h = y[None, :, 2]                                   # (1, M)
    r = x[:, None, :] - y[None, :, :]                   # (P, M, 3)
    ystar = y * _M
    big_r = x[:, None, :] - ystar[None, :, :]
    rn = np.sqrt(np.einsum("pmi,pmi->pm", r, r))
    rn = np.where(rn == 0, np.inf, rn)  # r = 0 only on the diagonal of a self-interaction matrix
    rrn = np.sqrt(np.einsum("pmi,pmi->pm", big_r, big_r))
    eye = np.eye(3)
    inv_r, inv_rr = 1.0 / rn, 1.0 / rrn
    s_r = eye[None, None] * inv_r[..., None, None] + r[..., :, None] * r[..., None, :] * (inv_r**3)[..., None, None]
    s_rr = (eye[None, None] * inv_rr[..., None, None]
            + big_r[..., :, None] * big_r[..., None, :] * (inv_rr**3)[..., None, None])
    r3 = big_r[..., 2]
    rr3, rr5 = inv_rr**3, inv_rr**5
    rr_outer = big_r[..., :, None] * big_r[..., None, :]
    e3 = eye[2]
    # D_ij = h(δ_ij/R³ - 3R_iR_j/R⁵) + δ_i3 R_j/R³ - (δ_ij R_3 + R_i δ_3j)/R³ + 3 R_i R_3 R_j/R⁵
    d = (h[..., None, None] * (eye * rr3[..., None, None] - 3.0 * rr_outer * rr5[..., None, None])
         + e3[:, None] * big_r[..., None, :] * rr3[..., None, None]
         - (eye * r3[..., None, None] + big_r[..., :, None] * e3[None, :]) * rr3[..., None, None]
         + 3.0 * rr_outer * (r3 * rr5)[..., None, None])
    g = s_r - s_rr + 2.0 * h[..., None, None] * _M[None, None, None, :] * d
    return np.transpose(g, (0, 2, 1, 3))


def blake_velocity(x: np.ndarray, y: np.ndarray, forces: np.ndarray, viscosity: float,
                   chunk: int = 2048) -> np.ndarray:
    """Velocity at ``x`` of point forces ``forces`` (on the fluid) at ``y`` above the wall.

    Parameters
    ----------
    x : ndarray, shape (P, 3)
    y : ndarray, shape (M, 3)
    forces : ndarray, shape (M, 3) or (K, M, 3)
        Forces [N]; a leading axis evaluates K force sets at once.
    viscosity : float
        Dynamic viscosity μ [Pa·s].

    Returns
    -------
    ndarray, shape (P, 3) or (K, P, 3)
    """
    forces = np.asarray(forces, float)
    single = forces.ndim == 2
    f = forces[None] if single else forces
    x = np.asarray(x, float)
    out = np.empty((f.shape[0], len(x), 3))
    for s in range(0, len(x), chunk):
        g = blake_tensor(x[s:s + chunk], y)
        out[:, s:s + chunk] = np.einsum("pimj,kmj->kpi", g, f)
    out /= 8.0 * np.pi * viscosity
    return out[0] if single else out


def regularized_blake_velocity(x: np.ndarray, y: np.ndarray, forces: np.ndarray, viscosity: float,
                               eps: float, chunk: int = 2048) -> np.ndarray:
    """Velocity at ``x`` ``(P, 3)`` of regularised Blake Stokeslets ``forces`` ``(K, M, 3)`` at ``y``.

    Same kernel as :func:`regularized_blake_tensor` applied to the forces directly, so
    maps of many points stay cheap: with ``r = x_p - y_m`` every sum over sources of the
    form ``Σ_m w_pm r_pmi`` is ``x_pi Σ_m w_pm - (w @ y)_pi``, so all work is in (P, M)
    scalars and matrix products. ``eps = 0`` gives the singular Blake solution.
    Returns ``(K, P, 3)``.
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    f = np.asarray(forces, float)
    if f.ndim == 2:
        f = f[None]
    h = y[:, 2]
    ystar = y * _M                                           # mirror points (y1, y2, -h)
    g = f * _M                                               # mirrored forces
    yf = np.einsum("mi,kmi->km", y, f)
    ysf = np.einsum("mi,kmi->km", ystar, f)
    ysg = np.einsum("mi,kmi->km", ystar, g)
    e2 = eps * eps
    out = np.empty((f.shape[0], len(x), 3))
    for s in range(0, len(x), chunk):
        xs = x[s:s + chunk]
        x2 = (xs * xs).sum(1)[:, None]
        xy = xs @ y.T
        r2 = np.maximum(x2 - 2 * xy + (y * y).sum(1)[None], 0.0)
        big2 = np.maximum(x2 - 2 * (xs @ ystar.T) + (ystar * ystar).sum(1)[None], 0.0)
        d3 = (r2 + e2) ** 1.5
        ib = 1.0 / np.sqrt(big2)
        ib3 = ib**3
        ib5 = ib3 * ib * ib
        r3 = xs[:, 2, None] + h[None]                         # R_3 = z + h
        w_direct = (r2 + 2 * e2) / d3
        c_g = 2 * h * (h - r3) * ib3
        for k in range(f.shape[0]):
            rf = xs @ f[k].T - yf[k][None]                    # r·f
            rrf = xs @ f[k].T - ysf[k][None]                  # R·f
            rrg = xs @ g[k].T - ysg[k][None]                  # R·g
            w_r = rf / d3                                     # multiplies r_i
            w_big = -rrf * ib3 + 6 * h * (r3 - h) * ib5 * rrg - 2 * h * ib3 * g[k][None, :, 2]   # multiplies R_i
            u = w_direct @ f[k] - ib @ f[k] + c_g @ g[k]
            u += xs * w_r.sum(1)[:, None] - w_r @ y
            u += xs * w_big.sum(1)[:, None] - w_big @ ystar
            u[:, 2] += (2 * h * ib3 * rrg).sum(1)
            out[k, s:s + chunk] = u
    return out / (8.0 * np.pi * viscosity)
