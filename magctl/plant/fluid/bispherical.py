"""Exact Stokes resistance of a sphere near a plane wall, in bispherical coordinates.

A sphere of radius ``a`` has its centre at height ``h`` above a no-slip plane; the gap is
``δ = h − a`` and the bispherical parameter ``α = arccosh(h/a)`` (the sphere is the surface
``ξ = α``, the plane ``ξ = 0``, and ``c = a sinh α``). Five problems are solved, each as an
infinite linear system truncated adaptively:

* **translation parallel to the wall** (O'Neill 1964, *Mathematika* 11, 67; Goldman, Cox &
  Brenner 1967a, *Chem. Eng. Sci.* 22, 637). The velocity is O'Neill's representation
  (his eq 6-9) in the functions ``w₁, Q₁, U₀, U₂`` with coefficients ``A_n … G_n``; the plane
  conditions give ``B_n, D_n, F_n`` from ``A_n`` (eq 13-15), the sphere conditions give
  ``C_n, E_n, G_n`` (eq 18-20) and continuity (eq 22) is the banded system for ``A_n``.
* **rotation about an axis parallel to the wall** (Dean & O'Neill 1963, *Mathematika* 10, 13,
  as corrected by Goldman, Cox & Brenner 1967a, their Table 2): the same system with the sphere
  velocity ``Ω × r``, which adds the terms in ``L_n`` to ``C_n`` and ``E_n``.
* **the sphere held fixed in the wall shear flow** ``u = γ z e_x`` (Goldman, Cox & Brenner
  1967b, *Chem. Eng. Sci.* 22, 653; O'Neill 1968): the disturbance equals ``−γ z e_x`` on the
  sphere, i.e. the translation condition with ``U`` replaced by ``−γ z``. On ``ξ = α``,
  ``z (cosh α − μ)^{-1/2} = c sinh α (cosh α − μ)^{-3/2}
  = 2√2 c Σ (n + ½) e^{−(n+½)α} P_n(μ)`` (the α-derivative of the generating function
  ``(cosh α − μ)^{-1/2} = √2 Σ e^{−(n+½)α} P_n(μ)``), so only the inhomogeneous term of
  ``E_n`` changes. The torque carries, besides O'Neill's series, the rigid-rotation part
  ``½ γ e_y × r`` of the boundary velocity, as in the rotation problem.
* **translation normal to the wall** (Brenner 1961, *Chem. Eng. Sci.* 16, 242, eq 2.19): the
  closed-form series for the drag factor λ.
* **the sphere held fixed in the axisymmetric wall flow** ``u_z = A z², u_ρ = −A ρ z`` (Goren &
  O'Neill 1971, *Chem. Eng. Sci.* 26, 325): Stimson & Jeffery's stream-function series as in
  Brenner (1961), four unknowns per n (:func:`stagnation_flow`).

Normalisation (Goldman, Cox & Brenner 1967a,b): a sphere translating with ``V`` along x feels
``F = 6πμaV f_t`` and torque ``T_y = 8πμa²V t_t``; rotating with ``Ω`` about y,
``F = 6πμa²Ω f_r`` and ``T_y = 8πμa³Ω t_r``; held fixed in ``u = γ z e_x``,
``F = 6πμahγ f_s`` and ``T_y = 4πμa³γ t_s``; translating normal to the wall with ``W``,
``F_z = −6πμaW λ``; held in ``u_z = A z²``, ``F_z = 6πμa g A h²``. Far from the wall
``f_t, t_r → −1``, ``f_s, t_s, λ, g → 1``, ``f_r, t_t → 0``; reciprocity gives
``f_r = (4/3) t_t`` (GCB 1967a, eq 3.12), which the two independent series satisfy to round-off.

**Truncation rule.** A system of ``N`` unknowns starts at ``N = ⌈16/α⌉ + 16`` (the
coefficients decay like ``e^{−2nα}``) and is doubled until every returned quantity changes
by less than ``rtol`` (default 1e-10, i.e. ≥ 9 stable significant digits) relative to its
value — absolute ``rtol`` for the cross terms ``f_r, t_t``, which vanish far from the wall.
Brenner's and the stagnation-flow series are summed the same way. The cost grows like 1/α ≈ (2δ/a)^{-1/2}: about
1 ms at δ/a = 1, 20 ms at δ/a = 1e-4. These are for building ``models/wall_resistance.toml``
and for tests; the simulation reads the table (:mod:`magctl.plant.fluid.wall_drag`).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

SQRT2 = np.sqrt(2.0)
MAX_TERMS = 400_000


def _alpha(gap_ratio) -> float:
    g = float(gap_ratio)
    if not np.isfinite(g) or g <= 0:
        raise ValueError(f"gap ratio delta/a must be finite and > 0, got {gap_ratio!r}")
    return float(np.arccosh(1.0 + g))


def _k(n, alpha):
    """``k_n = (n + ½) coth((n + ½)α) − coth α`` (O'Neill 1964, after eq 20)."""
    return (n + 0.5) / np.tanh((n + 0.5) * alpha) - 1.0 / np.tanh(alpha)


def _series(alpha: float, n_terms: int, e_inh, c_inh, rhs=None):
    """Solve O'Neill's system (eq 13-22) with inhomogeneous parts ``e_inh`` of ``E_n`` and
    ``c_inh`` of ``C_n`` (arrays over n = 0 … n_terms + 1); return the force sum
    ``Σ (E_n + n(n+1) C_n)`` and the torque sum of O'Neill's couple formula.

    ``rhs`` (n = 1 … N) replaces the right-hand side of eq 22 built from ``e_inh, c_inh``
    (the rotation problem, whose sphere condition on ``w₁`` also enters eq 22)."""
    m = n_terms + 2                                   # rows n = 0 … N+1 of C, E, G
    n = np.arange(m, dtype=float)
    k = _k(n, alpha)
    cols = n_terms + 3                                # A_0 … A_{N+2}; A_0 = A_{N+1} = A_{N+2} = 0
    nn = np.arange(m)

    def band(rows, shifts_vals):
        data, ri, ci = [], [], []
        for shift, val in shifts_vals:
            c = rows + shift
            ok = (c >= 0) & (c < cols)
            data.append(val[ok]), ri.append(rows[ok]), ci.append(c[ok])
        return sparse.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))), shape=(m, cols))

    safe = np.where(n >= 1, 2 * n - 1, 1.0)
    # eq 18: C_n = −2k_n [(n−1)A_{n−1}/(2n−1) − A_n + (n+2)A_{n+1}/(2n+3)], n ≥ 1
    on1 = (n >= 1).astype(float)
    cmat = band(nn, [(-1, on1 * -2 * k * (n - 1) / safe), (0, on1 * 2 * k), (1, on1 * -2 * k * (n + 2) / (2 * n + 3))])
    # eq 19: E_n = e_n + k_n [(n−1)n A_{n−1}/(2n−1) − (n+1)(n+2) A_{n+1}/(2n+3)], n ≥ 0
    emat = band(nn, [(-1, on1 * k * (n - 1) * n / safe), (1, -k * (n + 1) * (n + 2) / (2 * n + 3))])
    # eq 20: G_n = −k_n [A_{n−1}/(2n−1) − A_{n+1}/(2n+3)], n ≥ 2
    on2 = (n >= 2).astype(float)
    gmat = band(nn, [(-1, on2 * -k / safe), (1, on2 * k / (2 * n + 3))])
    ci = np.where(n >= 1, c_inh, 0.0)
    ei = e_inh
    # eq 22 for n = 1 … N
    r = np.arange(1, n_terms + 1)
    rf = r.astype(float)

    def comb(mat_or_vec, lin):
        return sum(sparse.diags(w) @ mat_or_vec[r + s] if sparse.issparse(mat_or_vec) else w * mat_or_vec[r + s]
                   for s, w in lin)

    lin_c = [(0, 5.0 + 0 * rf), (-1, -(rf - 1)), (1, rf + 2)]
    lin_e = [(-1, -1.0 + 0 * rf), (0, 2.0 + 0 * rf), (1, -1.0 + 0 * rf)]
    lin_g = [(-1, (rf - 2) * (rf - 1)), (0, -2 * (rf - 1) * (rf + 2)), (1, (rf + 2) * (rf + 3))]
    system = (comb(cmat, lin_c) + comb(emat, lin_e) + comb(gmat, lin_g)).tocsc()[:, 1:n_terms + 1]
    if rhs is None:
        rhs = -(comb(ci, lin_c) + comb(ei, lin_e))
    a_vec = np.zeros(cols)
    a_vec[1:n_terms + 1] = spsolve(system, rhs)
    c_n = cmat @ a_vec + ci
    e_n = emat @ a_vec + ei
    a_n = a_vec[:m]
    a_m1 = np.concatenate([[0.0], a_vec[:m - 1]])
    a_p1 = a_vec[1:m + 1]
    b_n = np.where(n >= 1, (n - 1) * a_m1 - (2 * n + 1) * a_n + (n + 2) * a_p1, 0.0)     # eq 13
    d_n = -0.5 * (n - 1) * n * a_m1 + 0.5 * (n + 1) * (n + 2) * a_p1                   # eq 14
    cth = 1.0 / np.tanh(alpha)
    ea = np.exp(-(2 * n + 1) * alpha)
    s_force = np.sum(e_n + n * (n + 1) * c_n)
    s_torque = np.sum((2 + ea) * (n * (n + 1) * (2 * a_n + c_n * cth) - (2 * n + 1 - cth) * e_n)
                      + (2 - ea) * (n * (n + 1) * b_n * cth - (2 * n + 1 - cth) * d_n))
    return s_force, s_torque


def _decay(n, alpha):
    """``e^{−(n+½)α} / sinh((n+½)α) = 2 / (e^{(2n+1)α} − 1)``, without overflow."""
    return 2.0 / np.expm1(np.minimum((2 * n + 1) * alpha, 700.0))


def _inv_sinh(n, alpha):
    """``1 / sinh((n+½)α)`` without overflow."""
    x = np.minimum((n + 0.5) * alpha, 700.0)
    return 2.0 * np.exp(-x) / -np.expm1(-2 * x)


def _problem(kind: str, alpha: float, n_terms: int):
    n = np.arange(n_terms + 2, dtype=float)
    sa = np.sinh(alpha)
    if kind == "translation":
        e = 2 * SQRT2 * _decay(n, alpha)
        sf, st = _series(alpha, n_terms, e, np.zeros_like(n))
        return -SQRT2 / 6 * sa * sf, sa**2 * st / (12 * SQRT2)                 # f_t, t_t
    if kind == "rotation":
        lam = -(np.exp(-(n - 0.5) * alpha) / (2 * n - 1) - np.exp(-(n + 1.5) * alpha) / (2 * n + 3)) / SQRT2
        e = SQRT2 * (2 * n + 1) * _decay(n, alpha) - lam / sa * _inv_sinh(n, alpha)
        c = 4 * lam / sa * _inv_sinh(n, alpha)
        # right-hand side of eq 22 for the rotating sphere (Dean & O'Neill 1963, eq 27, in the
        # scaling of our eq 22 rows: −2× theirs)
        r = n[1:n_terms + 1]
        brace = ((2 * r + 1) ** 2 * (np.exp(alpha) / (2 * r - 1) + np.exp(-alpha) / (2 * r + 3)) * _inv_sinh(r, alpha)
                 - (2 * r - 1) * _inv_sinh(r - 1, alpha) - (2 * r + 3) * _inv_sinh(r + 1, alpha))
        rhs = 2 * SQRT2 * np.exp(-(r + 0.5) * alpha) / ((2 * r + 1) * sa) * brace
        sf, st = _series(alpha, n_terms, e, c, rhs)
        return -SQRT2 / 6 * sa**2 * sf, -(1 - st * sa**3 / (4 * SQRT2)) / 3     # f_r, t_r
    if kind == "shear":
        e = -2 * SQRT2 * sa * (2 * n + 1) * _decay(n, alpha)
        sf, st = _series(alpha, n_terms, e, np.zeros_like(n))
        return -SQRT2 / 6 * sa * sf / np.cosh(alpha), sa**2 * st / (6 * SQRT2) + 1.0 / 3.0   # f_s, t_s
    raise ValueError(f"unknown problem {kind!r}")


def _converged(kind: str, gap_ratio: float, rtol: float):
    alpha = _alpha(gap_ratio)
    n_terms = int(np.ceil(16.0 / alpha)) + 16
    prev = np.asarray(_problem(kind, alpha, n_terms))
    while True:
        n_terms *= 2
        if n_terms > MAX_TERMS:
            raise RuntimeError(f"{kind} series at delta/a = {gap_ratio} did not converge within {MAX_TERMS} terms")
        cur = np.asarray(_problem(kind, alpha, n_terms))
        scale = np.abs(cur)
        if kind == "translation":
            scale = np.array([abs(cur[0]), 1.0])      # t_t → 0 far away: absolute
        elif kind == "rotation":
            scale = np.array([1.0, abs(cur[1])])      # f_r → 0 far away: absolute
        if np.all(np.abs(cur - prev) <= rtol * scale):
            return cur
        prev = cur


def _each(fn, gap_ratio, rtol):
    g = np.asarray(gap_ratio, float)
    out = np.array([fn(float(x), rtol) for x in g.ravel()])
    return tuple(out[:, i].reshape(g.shape) for i in range(out.shape[1]))


def parallel_translation(gap_ratio, rtol: float = 1e-10):
    """``(f_t, t_t)`` of a non-rotating sphere translating parallel to the wall (O'Neill 1964)."""
    return _each(lambda g, r: _converged("translation", g, r), gap_ratio, rtol)


def parallel_rotation(gap_ratio, rtol: float = 1e-10):
    """``(f_r, t_r)`` of a sphere rotating about an axis parallel to the wall (Dean & O'Neill 1963,
    corrected by Goldman, Cox & Brenner 1967a)."""
    return _each(lambda g, r: _converged("rotation", g, r), gap_ratio, rtol)


def shear_flow(gap_ratio, rtol: float = 1e-10):
    """``(f_s, t_s)`` of a sphere held fixed in the wall shear flow ``γ z e_x`` (Goldman, Cox &
    Brenner 1967b)."""
    return _each(lambda g, r: _converged("shear", g, r), gap_ratio, rtol)


def _brenner_sum(alpha: float, n_terms: int) -> float:
    n = np.arange(1, n_terms + 1, dtype=float)
    # numerator and denominator of eq 2.19 divided by e^{(2n+1)α}, with x = e^{−(2n+1)α}
    x = np.exp(-(2 * n + 1) * alpha)
    num = (1 - x * x) + (2 * n + 1) * np.sinh(2 * alpha) * x
    den = (1 - x) ** 2 - (2 * n + 1) ** 2 * np.sinh(alpha) ** 2 * x
    return 4.0 / 3.0 * np.sinh(alpha) * float(np.sum(n * (n + 1) / ((2 * n - 1) * (2 * n + 3)) * (num / den - 1)))


def _summed(series, gap_ratio: float, rtol: float, what: str) -> tuple[float, float]:
    """``(α, S)``: the series ``series(α, N)`` with N doubled until two sums agree to ``rtol``
    (starting at ⌈16/α⌉ + 16 terms, as the coefficient systems of the other problems)."""
    alpha = _alpha(gap_ratio)
    n_terms = int(np.ceil(16.0 / alpha)) + 16
    prev = series(alpha, n_terms)
    while True:
        n_terms *= 2
        if n_terms > MAX_TERMS:
            raise RuntimeError(f"{what} at delta/a = {gap_ratio} did not converge within {MAX_TERMS} terms")
        cur = series(alpha, n_terms)
        if abs(cur - prev) <= rtol * abs(cur):
            return alpha, cur
        prev = cur


def _brenner(gap_ratio: float, rtol: float) -> tuple[float]:
    return (_summed(_brenner_sum, gap_ratio, rtol, "Brenner's series")[1],)


def normal_translation(gap_ratio, rtol: float = 1e-10):
    """Brenner's (1961, eq 2.19) drag factor λ ≥ 1 of a sphere translating normal to the wall:
    ``λ = (4/3) sinh α Σ n(n+1)/((2n−1)(2n+3)) [(2 sinh(2n+1)α + (2n+1) sinh 2α) /
    (4 sinh²(n+½)α − (2n+1)² sinh²α) − 1]``."""
    return _each(_brenner, gap_ratio, rtol)[0]


def _stagnation_force(alpha: float, n_terms: int) -> float:
    """Stimson–Jeffery force sum of the disturbance of the flow ``ψ∞ = A ρ² z²/2`` (A = a = 1)."""
    n = np.arange(1, n_terms + 1, dtype=float)
    c = np.sinh(alpha)
    p, q = n - 0.5, n + 1.5
    e1, e2 = np.exp(-p * alpha), np.exp(-q * alpha)
    # g_n = e^{−pξ}/(2n−1) − e^{−qξ}/(2n+3) and its ξ-derivatives at ξ = α
    g1 = -0.5 * e1 + 0.5 * e2
    g2 = 0.5 * p * e1 - 0.5 * q * e2
    g3 = -0.5 * p**2 * e1 + 0.5 * q**2 * e2
    cth, csch2 = 1.0 / np.tanh(alpha), 1.0 / np.sinh(alpha) ** 2
    pref = 2 * SQRT2 / 3 * c**4 * n * (n + 1)
    phi = -pref * (g2 - cth * g1)                       # the disturbance equals −ψ∞ on the sphere …
    dphi = -pref * (g3 + csch2 * g1 - cth * g2)         # … and so does its ξ-derivative
    # U_n = a ch(pξ) + b sh(pξ) + c ch(qξ) + d sh(qξ); the plane gives c = −a, d = −p b / q
    # rows of the sphere conditions scaled by s = e^{−qα} against overflow at large n
    x1, x2 = np.exp(-2 * p * alpha), np.exp(-2 * q * alpha)
    s = np.exp(-q * alpha)
    ch1, sh1 = 0.5 * np.exp((p - q) * alpha) * (1 + x1), 0.5 * np.exp((p - q) * alpha) * (1 - x1)
    ch2, sh2 = 0.5 * (1 + x2), 0.5 * (1 - x2)
    m11, m12 = ch1 - ch2, sh1 - p / q * sh2
    m21, m22 = p * sh1 - q * sh2, p * (ch1 - ch2)
    det = m11 * m22 - m12 * m21
    b_n = (m11 * dphi * s - m21 * phi * s) / det          # (a_n drops out: a_n + c_n = 0)
    return 2 * np.pi * SQRT2 / c * float(np.sum(b_n * (1 - p / q)))   # a + b + c + d = b (1 − p/q)


def _stagnation(gap_ratio: float, rtol: float) -> tuple[float]:
    alpha, force = _summed(_stagnation_force, gap_ratio, rtol, "stagnation-flow series")
    # upward force over 6πμa A h² (the ambient vertical velocity at the centre)
    return (-force / (6 * np.pi * np.cosh(alpha) ** 2),)


def stagnation_flow(gap_ratio, rtol: float = 1e-10):
    """``g``: normal force ``F_z = 6πμa g u_z(h)`` on a sphere held fixed in the axisymmetric wall flow
    ``u_z = A z², u_ρ = −A ρ z`` (any smooth flow near a no-slip wall, to leading order in z),
    normalised by that flow's velocity at the centre ``u_z(h) = A h²`` (Goren & O'Neill 1971).

    Stimson & Jeffery's stream function ``ψ = (cosh ξ − μ)^{-3/2} Σ U_n(ξ) C_{n+1}^{-1/2}(μ)`` as in
    Brenner (1961), with the disturbance equal to ``−ψ∞`` on the sphere; ``ψ∞ = A ρ² z²/2`` expands
    through Brenner's eq 1.11 and ``sinh²ξ (cosh ξ − μ)^{-5/2} = (4/3)(∂²_ξ − coth ξ ∂_ξ)(cosh ξ − μ)^{-1/2}``,
    so each n is a 4×4 system; the force is Stimson & Jeffery's ``(2√2πμ/c) Σ (a_n + b_n + c_n + d_n)``.
    ``g → 1`` far from the wall (Faxén: ``1 + a²/3h²`` times the wall's λ), ``g → 3.2293`` at contact
    (Goren & O'Neill: 3.23).
    """
    return _each(_stagnation, gap_ratio, rtol)[0]


def resistance(gap_ratio, rtol: float = 1e-10):
    """All seven functions ``(f_t, f_r, t_t, t_r, f_s, t_s, λ)`` at gap ratios δ/a."""
    f_t, t_t = parallel_translation(gap_ratio, rtol)
    f_r, t_r = parallel_rotation(gap_ratio, rtol)
    f_s, t_s = shear_flow(gap_ratio, rtol)
    return f_t, f_r, t_t, t_r, f_s, t_s, normal_translation(gap_ratio, rtol)


def _pair_series(gap_ratio: float, kind: str) -> float:
    """Drag factor of one of two equal spheres moving along their line of centres (``kind`` "together":
    the same velocity; "approach": equal and opposite), surface gap ``gap_ratio`` in radii."""
    alpha = float(np.arccosh(1.0 + 0.5 * gap_ratio))
    n = np.arange(1.0, min(MAX_TERMS, np.ceil(340.0 / alpha)))       # e^{-(2n+1)α} is below 1e-290 beyond
    weight = n * (n + 1) / ((2 * n - 1) * (2 * n + 3))
    s1, s2, sa = np.sinh((2 * n + 1) * alpha), np.sinh(2 * alpha), np.sinh(alpha)
    if kind == "together":
        term = 1.0 - (4 * np.sinh((n + 0.5) * alpha) ** 2 - (2 * n + 1) ** 2 * sa**2) / (2 * s1 + (2 * n + 1) * s2)
    else:
        term = (4 * np.cosh((n + 0.5) * alpha) ** 2 + (2 * n + 1) ** 2 * sa**2) / (2 * s1 - (2 * n + 1) * s2) - 1.0
    return float(4.0 / 3.0 * np.sinh(alpha) * np.sum(weight * term))


def two_spheres_together(gap_ratio):
    """λ of two equal spheres translating with the same velocity along their line of centres (each feels
    ``6πμaUλ``), surface gap ``gap_ratio`` = δ/a: Stimson & Jeffery (1926, *Proc. R. Soc. A* 111, 110), the
    exact series in bispherical coordinates with ``cosh α = 1 + δ/2a``. λ → 0.6451 at contact."""
    return np.vectorize(lambda g: _pair_series(g, "together"), otypes=[float])(gap_ratio)


def two_spheres_approach(gap_ratio):
    """λ of two equal spheres approaching each other with equal and opposite velocities ``U`` (each feels
    ``6πμaUλ``): Maude (1961, *Br. J. Appl. Phys.* 12, 293) and Brenner (1961), the exact series; at small gaps
    ``λ = X¹¹_A − X¹²_A → a/(2δ) + (9/20) ln(a/δ) + O(1)`` (Jeffrey & Onishi 1984)."""
    return np.vectorize(lambda g: _pair_series(g, "approach"), otypes=[float])(gap_ratio)
