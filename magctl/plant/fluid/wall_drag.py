"""Near-wall hydrodynamics of a sphere resting on the glass (eq 4-5, 9).

Two modes give the in-plane velocity of a force- and torque-free sphere in the
robot's flow:

``paper``
    eq 4-5 exactly as printed: the Goldman-Cox-Brenner near-contact forces with
    the paper's bounds and the fitted rotation rate of eq 5.
``accurate``
    the full resistance functions at every gap: Goldman, Cox & Brenner's (1967)
    lubrication asymptotes for δ/a ≤ 0.01, the tabulated exact solution
    (``models/wall_resistance.toml``) for 0.1 ≤ δ/a ≤ 9, the method-of-reflections
    far field (Faxén; Goldman et al.) beyond, blended smoothly in log(δ/a).

Both treat the flow at the sphere centre ``U`` as a local shear ``U z / h`` (the
paper's assumption behind eq 4).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator

from magctl.config import load_model

ROT_BOUND = 0.5676
"""Upper bound of ΩR/V in eq 5."""


# --- paper mode: eq 4-5 ----------------------------------------------------------------------
def paper_coefficients(radius, gap, roughness):
    """``F*_shear, F*_trans, F*_rot`` of eq 4 with their bounds (``F*_trans < -1``, ``F*_rot > 0``).

    Parameters
    ----------
    radius : float
        R [m].
    gap : array_like
        δ, sphere-to-wall gap [m], ``>= 0``.
    roughness : float
        ε [m] (paper: ≈ 25 nm).
    """
    gap = np.asarray(gap, float)
    if np.any(gap < 0):
        raise ValueError("gap delta must be >= 0")
    if radius <= 0 or roughness <= 0:
        raise ValueError(f"radius {radius!r} and roughness {roughness!r} must be positive")
    h = radius + gap + roughness
    lg = np.log((gap + roughness) / radius)
    f_shear = 1.0 + 0.7005 * radius / h
    f_trans = np.minimum(8.0 / 15.0 * lg - 0.9588, -1.0)
    f_rot = np.maximum(-2.0 / 15.0 * lg - 0.2526, 0.0)
    return f_shear, f_trans, f_rot


def paper_rotation_ratio(radius, h):
    """ΩR/V_p of eq 5, bounded to ``[0, 0.5676]``."""
    q = radius / np.asarray(h, float)
    w = -2.375e-6 * np.exp(12.05 * q) + 1.025 * np.exp(-0.1438 * q)
    return np.clip(w, 0.0, ROT_BOUND)


def paper_mobility(radius, gap, roughness):
    """V_p/U for a sphere in the flow U at its centre from F_G = 0 (eq 4 with eq 5)."""
    f_shear, f_trans, f_rot = paper_coefficients(radius, gap, roughness)
    h = radius + np.asarray(gap, float) + roughness
    return -f_shear / (f_trans + paper_rotation_ratio(radius, h) * f_rot)


def paper_force(radius, viscosity, flow, velocity, gap, roughness):
    """F_G of eq 4 [N] for flow ``U`` and sphere velocity ``V_p`` (same shape, last axis components)."""
    f_shear, f_trans, f_rot = paper_coefficients(radius, gap, roughness)
    h = radius + np.asarray(gap, float) + roughness
    f_shear, f_trans, f_rot, rot = (np.asarray(a)[..., None] for a in (f_shear, f_trans, f_rot,
                                                                          paper_rotation_ratio(radius, h)))
    return 6 * np.pi * viscosity * radius * (flow * f_shear + velocity * (f_trans + rot * f_rot))


# --- accurate mode -----------------------------------------------------------------------------
def lubrication_coefficients(gap_ratio):
    """Goldman, Cox & Brenner (1967a,b) near-contact asymptotes ``(f_t, f_r, t_t, t_r, f_s, t_s)``."""
    lg = np.log(np.asarray(gap_ratio, float))
    return (8 / 15 * lg - 0.9588, -2 / 15 * lg - 0.2526, -0.1 * lg - 0.1895, 0.4 * lg - 0.3817,
            np.full_like(lg, 1.7005), np.full_like(lg, 0.9440))


def far_coefficients(gap_ratio):
    """Method-of-reflections far field: Faxén's parallel drag, Goldman et al.'s rotation and shear terms."""
    lam = 1.0 / (1.0 + np.asarray(gap_ratio, float))
    f_t = -1.0 / (1 - 9 / 16 * lam + lam**3 / 8 - 45 / 256 * lam**4 - lam**5 / 16)
    t_r = -1.0 / (1 - 5 / 16 * lam**3)
    zero = np.zeros_like(lam)
    return f_t, zero, zero, t_r, 1 + 9 / 16 * lam, 1 - 3 / 16 * lam**3


@lru_cache(maxsize=1)
def _table():
    t = load_model("wall_resistance").table
    x = np.log(t.gap)
    return x, [PchipInterpolator(x, getattr(t, k)) for k in ("f_t", "f_r", "t_t", "t_r", "f_s", "t_s")]


def _smoothstep(x, a, b):
    s = np.clip((x - a) / (b - a), 0.0, 1.0)
    return s * s * (3 - 2 * s)


def accurate_coefficients(gap_ratio):
    """Resistance functions ``(f_t, f_r, t_t, t_r, f_s, t_s)`` at gap δ/a (Goldman et al. normalisation)."""
    d = np.maximum(np.asarray(gap_ratio, float), 1e-12)
    lx = np.log(d)
    x, splines = _table()
    mid = [s(np.clip(lx, x[0], x[-1])) for s in splines]
    near = lubrication_coefficients(d)
    far = far_coefficients(d)
    w_near = 1.0 - _smoothstep(lx, np.log(0.01), x[0])      # lubrication → table
    w_far = _smoothstep(lx, x[-2], x[-1] + np.log(1.5))      # table → far field
    return tuple((w_near * n + (1 - w_near) * m) * (1 - w_far) + w_far * f
                 for n, m, f in zip(near, mid, far, strict=True))


def accurate_mobility(radius, gap, roughness):
    """V_p/U of a force- and torque-free sphere in the local shear flow ``U z / h``.

    Solves ``f_s U + f_t V + f_r aΩ = 0`` and ``t_t V + t_r aΩ + (a / 2h) t_s U = 0``.
    The roughness ε is added to the gap as in eq 4.
    """
    gap = np.asarray(gap, float)
    d = (gap + roughness) / radius
    f_t, f_r, t_t, t_r, f_s, t_s = accurate_coefficients(d)
    half = 0.5 * radius / (radius + gap + roughness)
    det = f_t * t_r - f_r * t_t
    return (-f_s * t_r + f_r * half * t_s) / det


def mobility(mode: str, radius, gap, roughness):
    """In-plane V_p/U for ``mode`` ``"paper"`` or ``"accurate"``."""
    if mode == "paper":
        return paper_mobility(radius, gap, roughness)
    if mode == "accurate":
        return accurate_mobility(radius, gap, roughness)
    raise ValueError(f"drag mode must be 'paper' or 'accurate', got {mode!r}")


def tabulate_resistance(gap_ratios, n_points: int = 900, source_radius: float = 0.8):
    """Resistance functions of a sphere near a wall from the Blake-Stokeslet solver.

    Returns an array ``(len(gap_ratios), 7)``: surface residual, f_t, f_r, t_t, t_r, f_s, t_s.
    This produced ``models/wall_resistance.toml``.
    """
    from magctl.plant.fluid.stokes import fibonacci_sphere, solve_rigid_body

    out = []
    for g in np.atleast_1d(gap_ratios):
        hh = 1.0 + float(g)
        c = np.array([0.0, 0.0, hh])
        col = c + fibonacci_sphere(n_points)
        src = c + source_radius * fibonacci_sphere(n_points // 3)
        v = np.zeros((3, n_points, 3))
        v[0, :, 0] = 1.0                                     # translation along x
        v[1] = np.cross([0.0, 1.0, 0.0], col - c)            # rotation about y
        v[2, :, 0] = -col[:, 2]                              # held fixed in the shear flow u = z e_x
        s = solve_rigid_body(col, src, v, 1.0)
        f, t = s.force_on_body(), s.torque_on_body(c)
        out.append([s.residual, f[0, 0] / (6 * np.pi), f[1, 0] / (6 * np.pi), t[0, 1] / (8 * np.pi),
                    t[1, 1] / (8 * np.pi), f[2, 0] / (6 * np.pi * hh), t[2, 1] / (4 * np.pi)])
    return np.asarray(out)
