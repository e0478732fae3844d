"""Near-wall hydrodynamics of a sphere resting on the glass (eq 4-5, 9).

Two modes give the in-plane velocity of a force- and torque-free sphere in the
robot's flow, and the normal drag of its gap balance:

``paper``
    eq 4-5 exactly as printed: the Goldman-Cox-Brenner near-contact forces with
    the paper's bounds and the fitted rotation rate of eq 5; eq 9's free-stream
    normal drag 6πμR.
``accurate``
    the exact Stokes resistance functions at every gap (:mod:`magctl.plant.fluid.bispherical`),
    tabulated in ``models/wall_resistance.toml`` for 1e-6 ≤ δ/a ≤ 100 (:func:`tabulate_exact`)
    and read as cubic splines in ln δ/a; below the table the near-contact expansions of
    Chaoui & Feuillebois (2003) and Cox & Brenner (1967), above it the method of reflections
    (Faxén; Goldman, Cox & Brenner 1967a,b; Lorentz), blended smoothly in ln δ/a. The normal
    drag is Brenner's (1961) 6πμRλ(δ).

Both treat the flow at the sphere centre ``U`` as a local shear ``U z / h`` (the
paper's assumption behind eq 4).
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numba.extending import register_jitable
from scipy.interpolate import CubicSpline

from magctl.config import load_model, models_dir

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
TABLE_RANGE = (1e-6, 100.0)
"""δ/a span of ``models/wall_resistance.toml``; below it the near-contact expansions, above it
the method of reflections, each blended over a factor 2 (below) / 1.5 (above) in δ/a."""
_POINTS_PER_DECADE = 16
_NAMES = ("f_t", "f_r", "t_t", "t_r", "f_s", "t_s", "lambda_n", "g_stag")

# Chaoui & Feuillebois (2003), Tables 11 and 13: near-contact expansions in δ = gap/a,
# leading logarithmic terms of O'Neill & Stewartson (1967) and Cooley & O'Neill (1969)
_CF_FT = ((-8 / 15, 0.954293724783876), (-64 / 375, 0.429450132564500))      # −f_t: (ln δ, 1) at δ^0, δ^1
_CF_TT = ((-1 / 10, -0.192952745666190), (-43 / 250, 0.100579155700110))     # t_t
_CF_TR = ((-2 / 5, 0.370892565890165), (-0.528001276176667, 0.340079923061464))   # −t_r
# sphere fixed in the wall shear flow at contact: the exact series of bispherical.shear_flow at
# δ/a → 0 (Goldman, Cox & Brenner 1967b give 1.7005 and 0.94399; O'Neill 1968 1.701, 0.944)
SHEAR_CONTACT = (1.700618, 0.943987)
# Cox & Brenner (1967): λ = 1/δ − (1/5) ln δ + 0.971264 + o(1)
_CB_NORMAL = 0.971264


@register_jitable
def _series(c, d, lg):
    """``l0 ln δ + c0 + δ (l1 ln δ + c1)`` for ``c = ((l0, c0), (l1, c1))``."""
    (l0, c0), (l1, c1) = c
    return l0 * lg + c0 + d * (l1 * lg + c1)


@register_jitable
def near_contact_terms(d):
    """The gap-dependent near-contact expansions at δ/a = ``d`` (array or float; compiled unchanged
    into :mod:`magctl.plant.sphere_kernel`): ``(f_t, f_r, t_t, t_r, λ)``.

    ``f_t, t_t, t_r`` to O(δ) with the O(δ ln δ) terms (Chaoui & Feuillebois 2003, Tables 11, 13),
    ``f_r = (4/3) t_t`` by reciprocity (Goldman, Cox & Brenner 1967a, eq 3.12), Brenner's normal
    drag factor ``λ = 1/δ − (1/5) ln δ + 0.971264`` (Cox & Brenner 1967). The shear-flow ``f_s, t_s``
    and the wall-flow ``g`` are their contact values :data:`SHEAR_CONTACT`, :data:`STAGNATION_CONTACT`.
    """
    lg = np.log(d)
    t_t = _series(_CF_TT, d, lg)
    return (-_series(_CF_FT, d, lg), 4.0 / 3.0 * t_t, t_t, -_series(_CF_TR, d, lg),
            1.0 / d - 0.2 * lg + _CB_NORMAL)


def lubrication_coefficients(gap_ratio):
    """Near-contact expansions ``(f_t, f_r, t_t, t_r, f_s, t_s)`` at δ/a ≪ 1.

    ``f_t, t_t, t_r`` to O(δ) with the O(δ ln δ) terms (Chaoui & Feuillebois 2003, Tables 11,
    13; error < 1e-8 at δ/a = 1e-5), ``f_r = (4/3) t_t`` by reciprocity (Goldman, Cox & Brenner
    1967a, eq 3.12), ``f_s, t_s`` their contact values (error O(δ)); :func:`near_contact_terms`.
    """
    d = np.asarray(gap_ratio, float)
    f_t, f_r, t_t, t_r, _ = near_contact_terms(d)
    return f_t, f_r, t_t, t_r, np.full_like(d, SHEAR_CONTACT[0]), np.full_like(d, SHEAR_CONTACT[1])


# force on a sphere held fixed in the wall flow u_z = A z² at contact, over 6πμa A h² (the exact
# series of bispherical.stagnation_flow at δ/a → 0; Goren & O'Neill 1971: 3.23)
STAGNATION_CONTACT = 3.229332


def lubrication_normal(gap_ratio):
    """Brenner's λ near contact: ``1/δ − (1/5) ln δ + 0.971264`` (Cox & Brenner 1967), and the
    stagnation-flow force factor ``g`` at its contact value (error O(δ)); :func:`near_contact_terms`."""
    d = np.asarray(gap_ratio, float)
    return near_contact_terms(d)[4], np.full_like(d, STAGNATION_CONTACT)


@register_jitable
def far_field_terms(d):
    """The method-of-reflections far field at δ/a = ``d`` (array or float; compiled unchanged into
    :mod:`magctl.plant.sphere_kernel`), in λ = a/h: ``(f_t, f_r, t_t, t_r, f_s, t_s, λ_n, g)``.

    Faxén's ``f_t = −1/(1 − 9/16 λ + 1/8 λ³ − 45/256 λ⁴ − 1/16 λ⁵)``; Goldman, Cox & Brenner
    (1967a, eq 2.64 and 3.8) ``t_t = (3/32) λ⁴ (1 − 3/8 λ)``, ``f_r = (4/3) t_t``,
    ``t_r = −(1 + 5/16 λ³)``; (1967b) ``f_s = 1 + 9/16 λ``, ``t_s = 1 − 3/16 λ³``; Brenner's normal
    drag factor by reflections (Lorentz, Faxén) ``λ_n = 1/(1 − 9/8 λ + 1/2 λ³)`` and the stagnation-flow
    factor ``g = λ_n (1 + λ²/3)`` (Faxén's Laplacian term). Powers as products, so that arrays and
    the compiled scalars take the same operations.
    """
    lam = 1.0 / (1.0 + d)
    lam2 = lam * lam
    lam3 = lam2 * lam
    lam4 = lam3 * lam
    lam5 = lam4 * lam
    f_t = -1.0 / (1 - 9 / 16 * lam + lam3 / 8 - 45 / 256 * lam4 - lam5 / 16)
    t_t = 3 / 32 * lam4 * (1 - 3 / 8 * lam)
    drag = 1.0 / (1 - 9 / 8 * lam + lam3 / 2)
    return (f_t, 4.0 / 3.0 * t_t, t_t, -(1 + 5 / 16 * lam3), 1 + 9 / 16 * lam, 1 - 3 / 16 * lam3,
            drag, drag * (1 + lam2 / 3))


def far_coefficients(gap_ratio):
    """Method-of-reflections far field ``(f_t, f_r, t_t, t_r, f_s, t_s)`` in λ = a/h
    (:func:`far_field_terms`: Faxén; Goldman, Cox & Brenner 1967a,b)."""
    return far_field_terms(np.asarray(gap_ratio, float))[:6]


def far_normal(gap_ratio):
    """Normal motion far from the wall, in λ = a/h: Brenner's drag factor by reflections (Lorentz,
    Faxén) ``1/(1 − 9/8 λ + 1/2 λ³)``, and the stagnation-flow factor ``g`` = that factor times Faxén's
    ``1 + λ²/3`` (the ambient flow's Laplacian term); :func:`far_field_terms`."""
    return far_field_terms(np.asarray(gap_ratio, float))[6:]


def tabulate_exact(path=None, points_per_decade: int = _POINTS_PER_DECADE):
    """Tabulate the seven exact functions (:mod:`magctl.plant.fluid.bispherical`) on a log grid of
    δ/a over :data:`TABLE_RANGE` and write ``models/wall_resistance.toml`` (or ``path``).

    Returns the grid and the ``(8, n)`` table. About half a minute on one core.
    """
    from magctl.plant.fluid.bispherical import resistance, stagnation_flow

    lo, hi = np.log10(TABLE_RANGE[0]), np.log10(TABLE_RANGE[1])
    n = int(round((hi - lo) * points_per_decade)) + 1
    grid = np.array([float(f"{g:.6g}") for g in np.logspace(lo, hi, n)])
    values = np.array([*resistance(grid), stagnation_flow(grid)])
    path = path if path is not None else models_dir() / "wall_resistance.toml"
    header = [
        "# Resistance functions of a sphere (radius a, centre height h = a + delta) near a plane no-slip wall.",
        "# Exact Stokes solutions in bispherical coordinates, regenerated by",
        "#   magctl.plant.fluid.wall_drag.tabulate_exact()   (module magctl.plant.fluid.bispherical):",
        "# translation parallel to the wall (O'Neill 1964), rotation about a parallel axis (Dean & O'Neill 1963",
        "# as corrected by Goldman, Cox & Brenner 1967a), the sphere held fixed in the wall shear flow",
        "# (Goldman, Cox & Brenner 1967b), translation normal to the wall (Brenner 1961, eq 2.19) and the sphere",
        "# held in the axisymmetric wall flow (Goren & O'Neill 1971); every",
        "# series truncated where 9 significant digits are stable. Log grid in delta/a, "
        f"{points_per_decade} points per decade.",
        "# Normalisation (Goldman, Cox & Brenner 1967a,b): force from translation F = 6 pi mu a V f_t; from",
        "# rotation F = 6 pi mu a^2 W f_r; torque from translation T = 8 pi mu a^2 V t_t; from rotation",
        "# T = 8 pi mu a^3 W t_r; shear flow u = g z: F = 6 pi mu a h g f_s, T = 4 pi mu a^3 g t_s; normal",
        "# translation with W: F = -6 pi mu a W lambda_n; sphere held in the wall flow u_z = A z^2, u_rho = -A rho z",
        "# (Goren & O'Neill 1971, same Stimson-Jeffery series as Brenner's): F = 6 pi mu a g_stag A h^2.",
        "",
        "[table]",
    ]
    src = "computed: magctl.plant.fluid.wall_drag.tabulate_exact (exact bispherical series, see header)"
    lines = [f'gap_ratio = {{ value = [{", ".join(f"{g:.10g}" for g in grid)}], '
             f'source = "assumed: log grid of delta/a, {points_per_decade} points per decade" }}']
    for name, row in zip(_NAMES, values, strict=True):
        lines.append(f'{name}_ratio = {{ value = [{", ".join(f"{v:.10g}" for v in row)}], source = "{src}" }}')
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(header + lines) + "\n")
    _table.cache_clear()
    return grid, values


class WallTable(NamedTuple):
    """The accurate mode's functions as plain arrays: on ``knots[i] ≤ x < knots[i+1]``
    (x = ln δ/a, clipped to the table) ``ln|f_j| = c_j3 + c_j2 s + c_j1 s² + c_j0 s³`` with
    ``s = x − knots[i]`` and ``coef[j, i] = (c_j0, c_j1, c_j2, c_j3)`` (scipy's ``PPoly`` layout),
    ``f_j = signs[j] e^{ln|f_j|}``; below ``near_hi`` blended with the expansions from ``near_lo``,
    above ``far_lo`` with the reflections up to ``far_hi`` (ln δ/a)."""

    knots: np.ndarray
    coef: np.ndarray
    signs: np.ndarray
    near_lo: float
    near_hi: float
    far_lo: float
    far_hi: float


@lru_cache(maxsize=1)
def _table():
    """One cubic spline of ln|f| against ln(δ/a) for the eight tabulated functions, and the same
    spline as the arrays of :class:`WallTable`."""
    t = load_model("wall_resistance").table
    x = np.log(np.asarray(t.gap, float))
    rows = []
    signs = []
    for name in _NAMES:
        y = np.asarray(getattr(t, name), float)
        sign = float(np.sign(y[0]))
        if not np.all(np.sign(y) == sign):
            raise ValueError(f"models/wall_resistance.toml: {name} changes sign; it cannot be interpolated in log")
        rows.append(np.log(sign * y))
        signs.append(sign)
    spline = CubicSpline(x, np.array(rows).T)
    table = WallTable(np.ascontiguousarray(spline.x), np.ascontiguousarray(spline.c.transpose(2, 1, 0)),
                      np.array(signs), float(x[0]), float(x[0] + np.log(2.0)), float(x[-1] - np.log(1.5)),
                      float(x[-1]))
    for a in (table.knots, table.coef, table.signs):
        a.flags.writeable = False
    return spline, table


def wall_table() -> WallTable:
    """The accurate mode's spline and blend bounds as arrays (``models/wall_resistance.toml``, read
    once), for the compiled frame (:mod:`magctl.plant.sphere_kernel`)."""
    return _table()[1]


@register_jitable
def smoothstep(x, a, b):
    """Cubic smoothstep ``3s² − 2s³`` of ``s = (x − a)/(b − a)`` clipped to [0, 1] (array or float)."""
    s = np.minimum(np.maximum((x - a) / (b - a), 0.0), 1.0)
    return s * s * (3 - 2 * s)


@register_jitable
def blend(w, edge, table):
    """``w · edge + (1 − w) · table``: the joint of the table with an expansion (array or float)."""
    return w * edge + (1 - w) * table


def _evaluate(gap_ratio):
    """The eight functions ``(8, …)`` at δ/a: table, blended with the expansions below and the
    reflections above it (evaluated only where a gap falls in a blend). The compiled frame takes
    the same steps per gap (``sphere_kernel.wall_functions``)."""
    d = np.asarray(gap_ratio, float)
    if np.any(~(d > 0)):
        raise ValueError("gap ratio delta/a must be > 0 (add the roughness to the gap)")
    flat = d.reshape(-1)
    lx = np.log(flat)
    spline, table = _table()
    out = table.signs[:, None] * np.exp(spline(np.clip(lx, table.near_lo, table.far_hi)).T)
    low = lx < table.near_hi
    if low.any():
        dl = flat[low]
        near = np.array([*lubrication_coefficients(dl), *lubrication_normal(dl)])
        w = 1.0 - smoothstep(lx[low], table.near_lo, table.near_hi)
        out[:, low] = blend(w, near, out[:, low])
    high = lx > table.far_lo
    if high.any():
        far = np.array(far_field_terms(flat[high]))
        w = smoothstep(lx[high], table.far_lo, table.far_hi)
        out[:, high] = blend(w, far, out[:, high])
    return out.reshape((len(_NAMES),) + d.shape)


def accurate_coefficients(gap_ratio):
    """Resistance functions ``(f_t, f_r, t_t, t_r, f_s, t_s)`` at gap δ/a (Goldman et al. normalisation).

    The exact solution tabulated in ``models/wall_resistance.toml`` (cubic spline of ln|f| in
    ln δ/a) over :data:`TABLE_RANGE`; below it :func:`lubrication_coefficients`, above it
    :func:`far_coefficients`, joined by cubic smoothsteps in ln δ/a over the table's end
    intervals (where both sides agree to < 1e-6 near and < 3e-5 far, so no joint is visible).
    """
    return tuple(_evaluate(gap_ratio)[:6])


def normal_resistance(gap_ratio):
    """Brenner's (1961) λ(δ/a): normal drag ``6πμaλ`` of a sphere at gap δ (tabulated exact series,
    :func:`lubrication_normal` below, :func:`far_normal` above, blended as :func:`accurate_coefficients`)."""
    return _evaluate(gap_ratio)[6]


def stagnation_factor(gap_ratio):
    """``g(δ/a)``: force ``6πμa g u_z(h)`` of the wall flow ``u_z ∝ z²`` on a held sphere (Goren &
    O'Neill 1971; :func:`magctl.plant.fluid.bispherical.stagnation_flow`), tabulated and blended as
    :func:`normal_resistance`."""
    return _evaluate(gap_ratio)[7]


def accurate_mobility(radius, gap, roughness):
    """V_p/U of a force- and torque-free sphere in the local shear flow ``U z / h``.

    Solves ``f_s U + f_t V + f_r aΩ = 0`` and ``t_t V + t_r aΩ + (a / 2h) t_s U = 0``
    (Goldman, Cox & Brenner 1967b, their free-sphere problem) with :func:`accurate_coefficients`.
    The roughness ε is added to the gap as in eq 4: ``δ/a = (gap + ε)/R``, ``h = R + gap + ε``.
    """
    gap = np.asarray(gap, float)
    d = (gap + roughness) / radius
    f_t, f_r, t_t, t_r, f_s, t_s = accurate_coefficients(d)
    half = 0.5 * radius / (radius + gap + roughness)
    det = f_t * t_r - f_r * t_t
    return (-f_s * t_r + f_r * half * t_s) / det


def normal_factors(mode: str, radius, gap, roughness):
    """``(λ, g)`` of the vertical balance: the sphere's normal drag is 6πμRλ and the flow's vertical
    velocity U_z at its centre pushes it with 6πμR g U_z. ``paper`` mode: λ = g = 1 (eq 9 as printed);
    ``accurate`` mode: Brenner's λ and Goren & O'Neill's g at δ/a = (gap + ε)/R."""
    gap = np.asarray(gap, float)
    if mode == "paper":
        return np.ones_like(gap), np.ones_like(gap)
    if mode == "accurate":
        values = _evaluate((gap + roughness) / radius)
        return values[6], values[7]
    raise ValueError(f"drag mode must be 'paper' or 'accurate', got {mode!r}")


def mobility(mode: str, radius, gap, roughness):
    """In-plane V_p/U for ``mode`` ``"paper"`` or ``"accurate"``."""
    if mode == "paper":
        return paper_mobility(radius, gap, roughness)
    if mode == "accurate":
        return accurate_mobility(radius, gap, roughness)
    raise ValueError(f"drag mode must be 'paper' or 'accurate', got {mode!r}")
