"""Lubrication between the robot and a sphere: the face film and the edge law (docs/fluid.md §5).

The robot's flow map (:mod:`magctl.plant.fluid.flow`) is solved without the sphere, so it
carries the robot's pull on a sphere only as far as the sphere samples that flow at its centre
(eq 4). Within a fraction of a radius of the robot's face the two bodies interact through the
thin oil film between them: approaching, the film resists being squeezed out; separating, it
resists being filled, and the sphere follows the robot. The normal resistance of a film of
minimum thickness ``h`` between surfaces of principal relative radii ``R_x, R_z`` is the
Reynolds-equation result

    F = 6πμ A V / h,      A = 2 (R_x R_z)^{3/2} / (R_x + R_z)

(:func:`film_area`; exact for the paraboloidal gap ``h + x²/2R_x + z²/2R_z``; ``A = R²`` for a
sphere against a plane, Brenner's 1961 leading term ``λ → a/h``, and ``A = a²/4`` for two equal
spheres, the leading term of Jeffrey & Onishi's 1984 ``X^A_11``). A face met at the sphere's equator
and curved in plan with curvature ``κ`` (1/m, positive concave) gives ``1/R_x = 1/a − κ`` against a
sphere of radius ``a``, ``R_z = a``.

The robot is tilted (front raised), so its faces are not all vertical: where a sphere resting on the
glass would meet a face's plane above or below that face, it meets the face's *edge* instead
(:func:`face_heights`; the front notch's bottom edge and the rear face's top edge). There the
three-body solution (:mod:`magctl.plant.fluid.three_body`) shows a coupling that grows like
``ln(1/h)``, not ``1/h``: the edge law ``6πμa C ln(h_e/h)``, with ``C`` and ``h_e`` fitted to it
(:func:`fit_edge_law`). :func:`film_laws` gives each footprint edge its law.

In the block (:mod:`magctl.plant.sphere_kernel`) the law's resistance ``R(h)`` is added to the sphere's
resistance to translation along the glass ``ζ`` only where the robot-only flow misses it: the face film
as its singular part ``6πμA (1/h − 1/h_f)`` below the cut-off ``h_f``, the edge law below ``h_e`` (both
zero and continuous at their cut-offs). The normal gap between robot and sphere is advanced exactly over
a sub-step with the flow and the robot's velocity held (:func:`film_gap`). Rough contact ends either at
``h_min`` (the asperities of robot and sphere): there the sphere is pushed by contact.
"""

from __future__ import annotations

import numpy as np
from numba.extending import register_jitable

from magctl.core.errors import ParameterError

CONFORMITY_CAP = 10.0
"""Largest ``R_x / a``: a face nearly as curved as the sphere is taken as ten radii conformal (the
paraboloidal gap does not hold beyond the face's edges, so the film's area cannot grow without bound)."""


def film_area(radius: float, curvature) -> np.ndarray:
    """``A`` [m²] of the film between a sphere of ``radius`` and a vertical face of plan ``curvature``
    (1/m, concave positive; 0 a flat face, negative a convex edge): ``2 (R_x R_z)^{3/2} / (R_x + R_z)``
    with ``1/R_x = 1/a − κ`` (capped at :data:`CONFORMITY_CAP` radii) and ``R_z = a``."""
    a = float(radius)
    if a <= 0:
        raise ParameterError(f"sphere radius must be positive, got {radius!r} m")
    inv = np.maximum(1.0 / a - np.asarray(curvature, float), 1.0 / (CONFORMITY_CAP * a))
    rx, rz = 1.0 / inv, a
    return 2.0 * (rx * rz) ** 1.5 / (rx + rz)


def edge_curvatures(vertices: np.ndarray) -> np.ndarray:
    """Signed plan curvature [1/m] of each edge ``k → k+1`` of a counter-clockwise polygon ``(V, 2)``:
    the mean of the curvatures of the circles through each end vertex and its neighbours (Menger
    curvature), positive where the outline is concave (an arc of radius ρ gives 1/ρ on its inner edges)."""
    v = np.asarray(vertices, float)
    prev, nxt = np.roll(v, 1, axis=0), np.roll(v, -1, axis=0)
    a, b = v - prev, nxt - v
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    chord = np.linalg.norm(nxt - prev, axis=1)
    at_vertex = -2.0 * cross / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) * chord)
    return 0.5 * (at_vertex + np.roll(at_vertex, -1))


def face_heights(geometry, radius: float) -> np.ndarray:
    """Per footprint edge, the height above the face's bottom rim (body ζ, [m]) at which a sphere of
    ``radius`` resting on the glass meets the plane of that edge's face.

    The face of an outline edge with outward body normal ``(n_x, n_y)`` has, once the body is tilted by
    θ about its resting edge (front raised: ``s = +1``), the world normal ``(n_x cos θ, n_y, s n_x sin θ)``;
    the sphere's point nearest that plane is ``a`` from its centre against the normal, at height
    ``a (1 − s n_x sin θ)``. Between 0 and the thickness the sphere meets the face; outside, an edge."""
    outline = geometry.outline
    d = np.roll(outline, -1, axis=0) - outline
    length = np.linalg.norm(d, axis=1)
    nx = d[:, 1] / length                                     # outward x component, counter-clockwise outline
    mid = outline + 0.5 * d
    s = 1.0 if geometry.raised_edge == "front" else -1.0
    contact = np.stack([mid[:, 0], mid[:, 1], np.zeros(len(mid))], axis=1)
    rim_height = geometry.to_frame(contact)[:, 2]            # the face's bottom rim under the edge's middle
    height = float(radius) * (1.0 - s * nx * np.sin(geometry.tilt))
    return (height - rim_height) / np.cos(geometry.tilt)


def film_laws(geometry, radius: float, edge_coefficient: float) -> tuple[np.ndarray, np.ndarray]:
    """Per footprint edge, the face film's ``A`` [m²] (:func:`film_area`) where a resting sphere meets the
    face (:func:`face_heights` within the thickness), else 0; and ``a C`` [m] of the edge law where it meets
    an edge, else 0."""
    zeta = face_heights(geometry, radius)
    on_face = (zeta >= 0.0) & (zeta <= geometry.thickness)
    area = np.where(on_face, film_area(radius, edge_curvatures(geometry.footprint)), 0.0)
    return area, np.where(on_face, 0.0, float(radius) * float(edge_coefficient))


def film_resistance(h, area, log_coef, face_cutoff: float, edge_cutoff: float) -> np.ndarray:
    """``R(h)/(6πμ)`` [m]: the face film's ``A (1/h − 1/h_f)`` below ``h_f`` plus the edge law's
    ``aC ln(h_e/h)`` below ``h_e``, each zero beyond its cut-off."""
    h = np.asarray(h, float)
    face = np.where(h < face_cutoff, area * (1.0 / h - 1.0 / face_cutoff), 0.0)
    edge = np.where(h < edge_cutoff, log_coef * np.log(edge_cutoff / np.minimum(h, edge_cutoff)), 0.0)
    return face + edge


def fit_edge_law(gaps, extra) -> tuple[float, float, float]:
    """The edge law ``C ln(h_e/h)`` fitted by least squares to resistances ``extra`` (in ``6πμa``) needed at
    ``gaps`` (in radii): ``extra = C (ln h_e − ln h)`` is linear in ``ln h``. Returns ``C``, ``h_e`` (radii)
    and the largest residual relative to ``extra``."""
    h, r = np.asarray(gaps, float), np.asarray(extra, float)
    if h.shape != r.shape or h.size < 2 or np.any(h <= 0) or np.any(r <= 0):
        raise ParameterError("fit_edge_law needs two or more positive gaps and resistances of one shape")
    slope, intercept = np.polyfit(-np.log(h), r, 1)
    fitted = intercept + slope * -np.log(h)
    return float(slope), float(np.exp(intercept / slope)), float(np.max(np.abs(fitted / r - 1.0)))


@register_jitable
def _film_integral(h, k_face, h_face, k_edge, h_edge):
    """``G(h) = ∫ (1 + R(s)/ζ) ds`` up to a constant: ``h + k_f (ln m_f − m_f/h_f) + k_e (m_e ln(h_e/m_e) + m_e)``,
    ``m = min(h, cut-off)``; increasing, with slope ``1 + R(h)/ζ``."""
    g = h
    if k_face > 0.0:
        m = min(h, h_face)
        g += k_face * (np.log(m) - m / h_face)
    if k_edge > 0.0:
        m = min(h, h_edge)
        g += k_edge * (m * np.log(h_edge / m) + m)
    return g


@register_jitable
def film_gap(h0, s, k_face, h_face, k_edge, h_edge, h_min):
    """Robot–sphere gap after a sub-step, at least ``h_min``: the root ``h₁`` of ``G(h₁) = G(h₀) + s``.

    With the lubrication resistance ``R(h)`` (face film ``6πμA(1/h − 1/h_f)``, edge law ``6πμaC ln(h_e/h)``)
    added to the sphere's ``ζ``, the gap obeys ``dh/dt = ζ w/(ζ + R(h))``, ``w`` the rate at which the flow
    alone would open it; so ``G(h) = ∫(1 + R/ζ) dh`` (:func:`_film_integral`) advances by ``s = w τ``.
    ``k_f = 6πμA/ζ``, ``k_e = 6πμaC/ζ`` [m]. Beyond both cut-offs ``G`` has slope 1 (solved directly);
    below, Newton's method in ``ln h₁`` kept inside a shrinking bracket (bisection where it leaves it).
    """
    target = _film_integral(h0, k_face, h_face, k_edge, h_edge) + s
    if target <= _film_integral(h_min, k_face, h_face, k_edge, h_edge):
        return h_min
    top = max(h0, h_face, h_edge)
    g_top = _film_integral(top, k_face, h_face, k_edge, h_edge)
    if target >= g_top:
        return top + (target - g_top)
    lo, hi = np.log(h_min), np.log(top)
    u = np.log(h0)
    for _ in range(100):
        h = np.exp(u)
        f = _film_integral(h, k_face, h_face, k_edge, h_edge) - target
        if f > 0.0:
            hi = u
        else:
            lo = u
        slope = 1.0
        if k_face > 0.0 and h < h_face:
            slope += k_face * (1.0 / h - 1.0 / h_face)
        if k_edge > 0.0 and h < h_edge:
            slope += k_edge * np.log(h_edge / h)
        step = f / (h * slope)
        if abs(step) <= 1e-15 * abs(u) or hi - lo <= 1e-15 * abs(u):     # converged to rounding
            return np.exp(u - step)
        nxt = u - step
        u = nxt if lo < nxt < hi else 0.5 * (lo + hi)
    return np.exp(u)
