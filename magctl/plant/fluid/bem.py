"""Boundary-element method for rigid bodies in Stokes flow above the no-slip glass.

Single-layer formulation (Pozrikidis 1992, *Boundary Integral and Singularity Methods
for Linearized Viscous Flow*, ch. 2 and 6): the flow of rigid bodies is

``u_i(x) = 1/(8πμ) Σ_panels ∫_panel G_ij(x, y) q_j dS_y``,

with ``q`` the force per area the surfaces exert on the fluid and ``G`` Blake's (1971)
tensor (:func:`magctl.plant.fluid.stokes.blake_tensor`), which vanishes on ``z = 0``
exactly, so the glass needs no panels. Surfaces are flat triangles carrying a constant
``q`` each; the boundary condition is collocated at the centroids.

Quadrature over a panel:

* self panel (the target lies in the panel): the free-space Stokeslet part
  ``δ_ij/r + r_i r_j/r³`` in polar coordinates about the target, which removes the 1/r
  singularity (Pozrikidis 1992 §6.3); each edge is integrated after the substitution
  ``t = t₀ + (d/L) sinh s`` that makes the integrand smooth; the image part by the rule below;
* every other pair (and the image part of the self panel): adaptive subdivision into four
  until the panel is small against its distance to the target *and* to the target's mirror
  point below the glass (the image singularity), then a 1-, 3- or 7-point Gauss rule
  (Dunavant 1985, degrees 1, 2, 5) by distance.

The near-singular cases of the robot (its 2 µm gap over the glass, neighbouring panels,
panels whose wall image is close, field points near the surface) all fall to the
subdivision. Panels can be tied to the unknowns of others with a sign per component
(mirror images: the robot's y → −y symmetry, the free surface's reflection about z = H),
so a symmetric problem is solved as the small system of its independent panels.

The rigid-body single layer has the normal ``n`` in its null space (∫ G·n dS = 0 outside a
closed surface); it is removed by the rank-one deflation ``A + v wᵀ`` with ``w = n·area`` of
each closed body, which leaves the solution of a compatible right-hand side unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg

# Dunavant (1985) rules on the reference triangle: barycentric points and weights (sum 1)
_A1, _B1, _W1 = 0.059715871789770, 0.470142064105115, 0.132394152788506
_A2, _B2, _W2 = 0.797426985353087, 0.101286507323456, 0.125939180544827
RULE7 = np.array([[1 / 3, 1 / 3, 1 / 3, 0.225],
                  [_A1, _B1, _B1, _W1], [_B1, _A1, _B1, _W1], [_B1, _B1, _A1, _W1],
                  [_A2, _B2, _B2, _W2], [_B2, _A2, _B2, _W2], [_B2, _B2, _A2, _W2]])
RULE3 = np.array([[2 / 3, 1 / 6, 1 / 6, 1 / 3], [1 / 6, 2 / 3, 1 / 6, 1 / 3], [1 / 6, 1 / 6, 2 / 3, 1 / 3]])
_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)

NEAR = 2.5
"""Subdivide a panel while its distance (to the target or the target's wall image) is below NEAR × its radius."""
MID = 6.0
"""7-point rule below MID × radius, 3-point rule below FAR × radius, centroid beyond."""
FAR = 25.0
MAX_DEPTH = 11
"""Largest number of subdivisions of a panel (a target on a panel's edge stops here)."""


@numba.njit(cache=True, nogil=True)
def _add_blake(x0, x1, x2, y0, y1, y2, w, acc, direct):
    """``acc += w G(x, y)`` (Blake 1971, eq 14, as :func:`stokes.blake_tensor`); without ``direct`` only
    the image part ``G − S(r)``."""
    h = y2
    b0, b1, b2 = x0 - y0, x1 - y1, x2 + h
    ib = 1.0 / np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    ib3 = ib * ib * ib
    big = (b0, b1, b2)
    cd = 2.0 * h * (h - b2) * ib3
    cr = 6.0 * h * (b2 - h) * ib3 * ib * ib
    c = 2.0 * h * ib3
    for i in range(3):
        for j in range(3):
            m = -1.0 if j == 2 else 1.0
            v = cr * big[i] * big[j]
            if i == j:
                v += cd
            if i == 2:
                v += c * big[j]
            if j == 2:
                v -= c * big[i]
            v = m * v - big[i] * big[j] * ib3
            if i == j:
                v -= ib
            acc[i, j] += w * v
    if direct:
        r0, r1, r2 = x0 - y0, x1 - y1, x2 - y2
        ir = 1.0 / np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        ir3 = ir * ir * ir
        r = (r0, r1, r2)
        for i in range(3):
            acc[i, i] += w * ir
            for j in range(3):
                acc[i, j] += w * r[i] * r[j] * ir3


@numba.njit(cache=True, nogil=True)
def _tri_area(t):
    ax, ay, az = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    bx, by, bz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)


@numba.njit(cache=True, nogil=True)
def _adaptive(x, tri, acc, direct, rule7, rule3):
    """``acc += ∫_tri G(x, y) dS_y`` (image part only without ``direct``) by adaptive subdivision."""
    stack = np.empty((4 * MAX_DEPTH + 4, 3, 3))
    depth = np.empty(4 * MAX_DEPTH + 4, np.int64)
    stack[0] = tri
    depth[0] = 0
    n = 1
    xs2 = -x[2]
    while n > 0:
        n -= 1
        t = stack[n].copy()
        dep = depth[n]
        c0 = (t[0, 0] + t[1, 0] + t[2, 0]) / 3.0
        c1 = (t[0, 1] + t[1, 1] + t[2, 1]) / 3.0
        c2 = (t[0, 2] + t[1, 2] + t[2, 2]) / 3.0
        rho = 0.0
        for k in range(3):
            d = np.sqrt((t[k, 0] - c0) ** 2 + (t[k, 1] - c1) ** 2 + (t[k, 2] - c2) ** 2)
            rho = max(rho, d)
        dimg = np.sqrt((x[0] - c0) ** 2 + (x[1] - c1) ** 2 + (xs2 - c2) ** 2)
        dist = dimg
        if direct:
            dist = min(dist, np.sqrt((x[0] - c0) ** 2 + (x[1] - c1) ** 2 + (x[2] - c2) ** 2))
        if dist > NEAR * rho or dep >= MAX_DEPTH:
            area = _tri_area(t)
            if dist > FAR * rho:
                _add_blake(x[0], x[1], x[2], c0, c1, c2, area, acc, direct)
            else:
                rule = rule7 if dist < MID * rho else rule3
                for q in range(rule.shape[0]):
                    y0 = rule[q, 0] * t[0, 0] + rule[q, 1] * t[1, 0] + rule[q, 2] * t[2, 0]
                    y1 = rule[q, 0] * t[0, 1] + rule[q, 1] * t[1, 1] + rule[q, 2] * t[2, 1]
                    y2 = rule[q, 0] * t[0, 2] + rule[q, 1] * t[1, 2] + rule[q, 2] * t[2, 2]
                    _add_blake(x[0], x[1], x[2], y0, y1, y2, rule[q, 3] * area, acc, direct)
            continue
        m01 = 0.5 * (t[0] + t[1])
        m12 = 0.5 * (t[1] + t[2])
        m20 = 0.5 * (t[2] + t[0])
        for a, b, cc in ((t[0], m01, m20), (m01, t[1], m12), (m20, m12, t[2]), (m01, m12, m20)):
            stack[n, 0] = a
            stack[n, 1] = b
            stack[n, 2] = cc
            depth[n] = dep + 1
            n += 1


@numba.njit(cache=True, nogil=True)
def _polar_stokeslet(x, tri, acc, gl_x, gl_w):
    """``acc += ∫_tri (δ_ij/r + r_i r_j/r³) dS_y`` for ``x`` in the panel (polar coordinates about ``x``).

    Over the sub-triangle ``(x, a, b)`` the polar integral is ``∫ (I + r̂r̂) R(θ) dθ``; along the edge
    ``q(t) = a + t (b − a)`` this is ``∫₀¹ (I + r̂r̂) 2A/|q − x| dt`` (A the sub-triangle's area), and
    ``t = t₀ + (d/L) sinh s`` (t₀ the foot of the perpendicular, d its length, L = |b − a|) turns
    ``dt/|q − x|`` into ``ds/L``, leaving a bounded integrand for Gauss–Legendre.
    """
    for e in range(3):
        a = tri[e]
        b = tri[(e + 1) % 3]
        ab = b - a
        ln = np.sqrt((ab * ab).sum())
        ax = a - x
        t0 = -(ax * ab).sum() / (ln * ln)
        foot = ax + t0 * ab
        d = np.sqrt((foot * foot).sum())
        if d < 1e-12 * ln:
            continue                                   # x on this edge's line: the sub-triangle is empty
        two_a = d * ln
        s_lo = np.arcsinh((0.0 - t0) * ln / d)
        s_hi = np.arcsinh((1.0 - t0) * ln / d)
        half = 0.5 * (s_hi - s_lo)
        mid = 0.5 * (s_hi + s_lo)
        for k in range(gl_x.shape[0]):
            s = mid + half * gl_x[k]
            t = t0 + d / ln * np.sinh(s)
            r = ax + t * ab
            rn = np.sqrt((r * r).sum())
            w = gl_w[k] * half * two_a / ln
            for i in range(3):
                acc[i, i] += w
                for j in range(3):
                    acc[i, j] += w * r[i] * r[j] / (rn * rn)


@numba.njit(cache=True, nogil=True)
def _panel_integral(x, tri, own, acc, rule7, rule3, gl_x, gl_w):
    if own:
        _polar_stokeslet(x, tri, acc, gl_x, gl_w)
        _adaptive(x, tri, acc, False, rule7, rule3)
    else:
        _adaptive(x, tri, acc, True, rule7, rule3)


@numba.njit(cache=True, nogil=True)
def _source(x, xr, tri, own, reflect, acc, rule7, rule3, gl_x, gl_w):
    """One panel's integral at ``x``; a reflected copy (``reflect`` = c, not NaN) is evaluated at the mirror
    point ``xr`` of ``x`` in the plane ``z = c`` and its z row flipped: ``P ∫ G(Px, y) dS``."""
    acc[:] = 0.0
    if np.isnan(reflect):
        _panel_integral(x, tri, own, acc, rule7, rule3, gl_x, gl_w)
    else:
        xr[0] = x[0]
        xr[1] = x[1]
        xr[2] = 2.0 * reflect - x[2]
        _panel_integral(xr, tri, False, acc, rule7, rule3, gl_x, gl_w)
        for j in range(3):
            acc[2, j] = -acc[2, j]


@numba.njit(cache=True, parallel=True)
def _assemble(targets, own, tris, unknown, sign, reflect, n_unknown, rule7, rule3, gl_x, gl_w):
    """``A[p, i, u, j] = Σ_{s: unknown[s] = u} ∫_{tris[s]} G_ij(targets[p], y) dS sign[s, j]`` (reflected
    copies as in :func:`_source`)."""
    p_count = targets.shape[0]
    out = np.zeros((p_count, 3, n_unknown, 3))
    for p in numba.prange(p_count):
        acc = np.zeros((3, 3))
        xr = np.zeros(3)
        x = targets[p].copy()
        for s in range(tris.shape[0]):
            _source(x, xr, tris[s], own[p] == s, reflect[s], acc, rule7, rule3, gl_x, gl_w)
            u = unknown[s]
            for i in range(3):
                for j in range(3):
                    out[p, i, u, j] += acc[i, j] * sign[s, j]
    return out


@numba.njit(cache=True, parallel=True)
def _evaluate(points, own, tris, density, reflect, rule7, rule3, gl_x, gl_w):
    """``u[k, p, i] = Σ_s ∫_{tris[s]} G_ij(points[p], y) dS density[k, s, j]`` (no 1/(8πμ))."""
    k_count = density.shape[0]
    out = np.zeros((k_count, points.shape[0], 3))
    for p in numba.prange(points.shape[0]):
        acc = np.zeros((3, 3))
        xr = np.zeros(3)
        x = points[p].copy()
        for s in range(tris.shape[0]):
            _source(x, xr, tris[s], own[p] == s, reflect[s], acc, rule7, rule3, gl_x, gl_w)
            for k in range(k_count):
                for i in range(3):
                    out[k, p, i] += acc[i, 0] * density[k, s, 0] + acc[i, 1] * density[k, s, 1] \
                        + acc[i, 2] * density[k, s, 2]
    return out


def _check_tris(tris: np.ndarray, name: str) -> np.ndarray:
    tris = np.ascontiguousarray(tris, dtype=float)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3) or len(tris) == 0:
        raise ValueError(f"{name} must be triangles (T >= 1, 3, 3), got shape {tris.shape}")
    if np.any(tris[..., 2] <= 0):
        raise ValueError(f"{name}: every panel must lie above the glass (z > 0)")
    return tris


def centroids(tris: np.ndarray) -> np.ndarray:
    """Panel centroids ``(T, 3)``."""
    return tris.mean(axis=1)


def areas(tris: np.ndarray) -> np.ndarray:
    """Panel areas ``(T,)``."""
    return 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)


def normals(tris: np.ndarray) -> np.ndarray:
    """Unit normals ``(T, 3)`` by the right-hand rule on the vertex order."""
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _reflect(reflect, n: int) -> np.ndarray:
    if reflect is None:
        return np.full(n, np.nan)
    out = np.ascontiguousarray(reflect, dtype=float)
    if out.shape != (n,):
        raise ValueError(f"reflect needs one plane height (or NaN) per panel ({n}), got shape {out.shape}")
    return out


def single_layer(targets: np.ndarray, tris: np.ndarray, own: np.ndarray | None = None,
                 unknown: np.ndarray | None = None, sign: np.ndarray | None = None,
                 n_unknown: int | None = None, reflect: np.ndarray | None = None) -> np.ndarray:
    """Integrated Blake tensor ``(P, 3, U, 3)``: ``∫_panel G_ij(x_p, y) dS_y`` summed into unknowns.

    ``own[p]`` is the index of the panel that contains target ``p`` (−1 if none: then the target
    must not lie on any panel); panel ``s`` adds to unknown ``unknown[s]`` with the component
    signs ``sign[s]`` (defaults: one unknown per panel, signs +1); ``reflect[s]`` (NaN: none) makes
    panel ``s`` a copy seen through the mirror ``z = reflect[s]`` (see :class:`PanelSet`). Divide by
    ``8πμ`` for velocity.
    """
    tris = _check_tris(tris, "panels")
    targets = np.ascontiguousarray(targets, dtype=float).reshape(-1, 3)
    own = np.full(len(targets), -1, np.int64) if own is None else np.asarray(own, np.int64)
    unknown = np.arange(len(tris)) if unknown is None else np.asarray(unknown, np.int64)
    sign = np.ones((len(tris), 3)) if sign is None else np.ascontiguousarray(sign, dtype=float)
    n_unknown = int(unknown.max()) + 1 if n_unknown is None else int(n_unknown)
    return _assemble(targets, own, tris, unknown, sign, _reflect(reflect, len(tris)), n_unknown, RULE7, RULE3,
                     _GL_X, _GL_W)


def layer_velocity(points: np.ndarray, tris: np.ndarray, density: np.ndarray, viscosity: float,
                   own: np.ndarray | None = None, reflect: np.ndarray | None = None, chunk: int = 4096) -> np.ndarray:
    """Velocity ``(K, P, 3)`` at ``points (P, 3)`` of panels ``tris (S, 3, 3)`` with force densities
    ``density (K, S, 3)`` [N/m²] (``own`` and ``reflect`` as in :func:`single_layer`)."""
    tris = _check_tris(tris, "panels")
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    density = np.ascontiguousarray(density, dtype=float)
    if density.ndim == 2:
        density = density[None]
    if density.shape[1:] != (len(tris), 3):
        raise ValueError(f"density shape {density.shape} does not match {len(tris)} panels")
    own = np.full(len(points), -1, np.int64) if own is None else np.asarray(own, np.int64)
    reflect = _reflect(reflect, len(tris))
    out = np.empty((density.shape[0], len(points), 3))
    for s in range(0, len(points), chunk):
        out[:, s:s + chunk] = _evaluate(points[s:s + chunk], own[s:s + chunk], tris, density, reflect, RULE7,
                                        RULE3, _GL_X, _GL_W)
    return out / (8.0 * np.pi * viscosity)


@dataclass
class PanelSet:
    """Panels whose force densities are tied to a set of unknowns.

    The first ``n_independent`` panels carry the unknowns ``0 .. n−1`` in order; every other panel
    is a copy (a mirror image) of one of them, its density the unknown's times ``sign``. A copy with
    ``reflect = c`` (not NaN) adds the flow seen through the mirror plane ``z = c``:
    ``u(x) = P ∫ G(Px, y) q dS`` with ``P`` the reflection — the image that makes ``z = c`` a plane of
    symmetry (a free surface: zero normal velocity and zero shear stress).

    Attributes
    ----------
    tris : ndarray (S, 3, 3)
        Triangles [m], vertex order giving outward normals (right-hand rule).
    unknown : ndarray (S,) int
        Unknown carried by each panel.
    sign : ndarray (S, 3)
        Component signs that map the unknown to this panel's density (+1 for the independent panels).
    body : ndarray (S,) int
        Closed body the panel belongs to (for the null-space deflation); −1 for an open sheet (a lid).
    n_independent : int
    reflect : ndarray (S,), optional
        Mirror plane height of a reflected copy, NaN for none (the default).
    """

    tris: np.ndarray
    unknown: np.ndarray
    sign: np.ndarray
    body: np.ndarray
    n_independent: int
    reflect: np.ndarray | None = None

    def __post_init__(self):
        self.tris = _check_tris(self.tris, "panels")
        s = len(self.tris)
        self.unknown = np.asarray(self.unknown, np.int64)
        self.sign = np.ascontiguousarray(self.sign, dtype=float)
        self.body = np.asarray(self.body, np.int64)
        self.reflect = _reflect(self.reflect, s)
        n = int(self.n_independent)
        if self.unknown.shape != (s,) or self.sign.shape != (s, 3) or self.body.shape != (s,):
            raise ValueError(f"unknown, sign and body must describe all {s} panels")
        if not (0 < n <= s and np.array_equal(self.unknown[:n], np.arange(n)) and self.unknown.max() < n):
            raise ValueError("the first n_independent panels must carry unknowns 0 .. n-1 in order, the rest copies")

    def densities(self, q: np.ndarray) -> np.ndarray:
        """Density ``(..., S, 3)`` on every panel from the unknowns ``(..., n, 3)``."""
        return q[..., self.unknown, :] * self.sign


def solve(panels: PanelSet, boundary_velocity: np.ndarray, viscosity: float, deflate: bool) -> np.ndarray:
    """Force densities ``(K, S, 3)`` [N/m²] on every panel for K rigid motions of one symmetry.

    The collocation points are the independent panels' centroids and ``boundary_velocity
    (K, n_independent, 3)`` the velocity the flow must have there (zero on a lid); one LU
    factorisation serves all K. ``deflate`` removes each closed body's normal (pressure) mode —
    set it when that mode has the symmetry of the copies' signs (even under the mirror).
    """
    n = panels.n_independent
    rhs = np.asarray(boundary_velocity, float)
    if rhs.ndim == 2:
        rhs = rhs[None]
    if rhs.ndim != 3 or rhs.shape[1:] != (n, 3):
        raise ValueError(f"boundary velocity shape {rhs.shape} does not match {n} collocation panels")
    tris = panels.tris
    x = centroids(tris[:n])
    if not np.all(np.isnan(panels.reflect[:n])):
        raise ValueError("the independent panels cannot be reflected copies")
    a = _assemble(x, np.arange(n), tris, panels.unknown, panels.sign, panels.reflect, n,
                  RULE7, RULE3, _GL_X, _GL_W).reshape(3 * n, 3 * n)
    a /= 8.0 * np.pi * viscosity
    if deflate:
        nrm, area = normals(tris[:n]), areas(tris[:n])
        scale = np.abs(np.diagonal(a)).mean()
        for b in np.unique(panels.body[:n]):
            if b < 0:
                continue
            sel = panels.body[:n] == b
            v = np.zeros((n, 3))
            v[sel] = nrm[sel]
            w = v * area[:, None] / area[sel].sum()
            a += scale * np.outer(v.ravel(), w.ravel())
    q = scipy.linalg.solve(a, rhs.reshape(len(rhs), 3 * n).T, assume_a="gen", overwrite_a=True,
                           check_finite=False)
    return panels.densities(q.T.reshape(len(rhs), n, 3))


def mirrored(tris: np.ndarray, axis: int, plane: float = 0.0) -> np.ndarray:
    """Triangles reflected in the plane ``x_axis = plane``, vertex order reversed (normals stay outward)."""
    out = tris[:, ::-1].copy()
    out[..., axis] = 2.0 * plane - out[..., axis]
    return out


def y_symmetric(half: np.ndarray, body=0) -> tuple[PanelSet, PanelSet]:
    """The even and odd :class:`PanelSet` of panels mirror-symmetric about ``y = 0`` from their ``y > 0`` half
    (``body``: one body index for all, or one per panel, −1 for an open sheet).

    Even (motion along x or z): the mirror panel carries ``(q_x, −q_y, q_z)``; odd (along y):
    ``(−q_x, q_y, −q_z)``.
    """
    n = len(half)
    tris = np.concatenate([half, mirrored(half, 1)])
    unknown = np.concatenate([np.arange(n), np.arange(n)])
    body_ = np.concatenate([np.broadcast_to(np.asarray(body, np.int64), (n,))] * 2)
    out = []
    for par in ((1.0, -1.0, 1.0), (-1.0, 1.0, -1.0)):
        sign = np.concatenate([np.ones((n, 3)), np.tile(par, (n, 1))])
        out.append(PanelSet(tris, unknown, sign, body_, n))
    return out[0], out[1]
