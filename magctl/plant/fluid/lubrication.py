"""Squeeze-film lubrication between the robot's face and a sphere (docs/fluid.md §7).

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
spheres, the leading term of Jeffrey & Onishi's 1984 ``X^A_11``). The robot's face is vertical in
the footprint model and its outline curved in plan: a concave face of curvature ``κ`` (1/m,
positive concave) gives ``1/R_x = 1/a − κ`` against a sphere of radius ``a``, ``R_z = a``.

In the block (:mod:`magctl.plant.sphere_kernel`) the film's resistance is added to the sphere's
resistance to translation along the glass ``ζ`` only where the robot-only flow misses it, as the
singular part ``6πμA (1/h − 1/h_c)`` below the cut-off ``h_c`` (zero and continuous at ``h_c``),
and the normal gap between face and sphere is advanced exactly over a sub-step with the flow and the
robot's velocity held (:func:`film_gap`). Rough contact ends the film at ``h_min`` (the asperities of
robot and sphere): there the sphere is pushed by contact.
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


@register_jitable
def film_gap(h0, s, kappa):
    """Face–sphere gap after a sub-step: the root ``h₁ > 0`` of ``(h₁ − h₀) + κ ln(h₁/h₀) = s``.

    With the film's resistance ``6πμA/h`` added to the sphere's ``ζ'`` (its resistance to translation
    along the glass less the film's value at the cut-off), the gap obeys ``dh/dt = (ζ/ζ') w h/(h + κ)``,
    ``κ = 6πμA/ζ'``, where ``w`` is the rate at which the flow alone would open it; ``s = (ζ/ζ') w τ``.
    Newton's method in ``ln h₁`` (the left side is increasing and concave in it: converges from ``h₀``).
    """
    u = np.log(h0)
    lh0 = u
    for _ in range(60):
        e = np.exp(u)
        f = e - h0 + kappa * (u - lh0) - s
        step = f / (e + kappa)
        u -= step
        if abs(step) < 1e-12:
            break
    return np.exp(u)
