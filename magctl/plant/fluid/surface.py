"""Surface forces between a sphere and the glass under oil: work of adhesion and JKR pull-off (eq 1-3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.config import load_model
from magctl.core.errors import ParameterError


def work_of_adhesion_pair(gamma_j, gamma_k):
    """Work of adhesion between two materials, eq 1: ``W_jk ≈ 2 sqrt(γ_j γ_k)`` [J/m²]."""
    gj, gk = np.asarray(gamma_j, float), np.asarray(gamma_k, float)
    if np.any(gj < 0) or np.any(gk < 0):
        raise ValueError(f"surface energies must be non-negative, got {gamma_j!r} and {gamma_k!r}")
    return 2.0 * np.sqrt(gj * gk)


def work_of_adhesion(gamma_1, gamma_2, gamma_3):
    """Work of adhesion of material 1 on material 2 across medium 3, eq 2 [J/m²].

    ``W_132 = W_12 + W_33 - W_13 - W_23`` with every ``W_jk`` from eq 1.
    Positive values attract, negative values repel.
    """
    return (work_of_adhesion_pair(gamma_1, gamma_2) + work_of_adhesion_pair(gamma_3, gamma_3)
            - work_of_adhesion_pair(gamma_1, gamma_3) - work_of_adhesion_pair(gamma_2, gamma_3))


def jkr_pull_off(radius, w132):
    """JKR pull-off force of a sphere on a flat, eq 3: ``P = 1.5 π R W_132`` [N]."""
    radius = np.asarray(radius, float)
    if np.any(radius <= 0):
        raise ValueError(f"sphere radius must be positive, got {radius!r} m")
    return 1.5 * np.pi * radius * np.asarray(w132, float)


@dataclass(frozen=True)
class PullOffRange:
    """Range of the pull-off force P over the surface-energy ranges of Table I.

    Attributes
    ----------
    w132_min, w132_max : float
        Work of adhesion at the ends of the range [J/m²].
    p_min, p_max : float
        Pull-off force at the ends of the range [N].
    """

    w132_min: float
    w132_max: float
    p_min: float
    p_max: float


def pull_off_range(radius: float, materials=None) -> PullOffRange:
    """Pull-off range of a polystyrene sphere on glass under silicone oil (paper §IV-A).

    Parameters
    ----------
    radius : float
        Sphere radius [m].
    materials : Params, optional
        ``models/materials.toml`` (loaded when omitted).

    Notes
    -----
    W_132 = 2(√γ1 − √γ3)(√γ2 − √γ3) rises with the substrate energy γ2 and falls with
    the fluid energy γ3 (for γ1, γ2 > γ3), so the extremes pair the low end of glass with the
    high end of oil and vice versa.
    """
    m = materials if materials is not None else load_model("materials")
    g1 = m.polystyrene.surface_energy
    g2 = (m.glass.surface_energy_min, m.glass.surface_energy_max)
    g3 = (m.silicone_oil.surface_energy_min, m.silicone_oil.surface_energy_max)
    if min(g1, *g2, *g3) <= 0:
        raise ParameterError(f"{m._path}: surface energies must be positive")
    corners = [work_of_adhesion(g1, a, b) for a in g2 for b in g3]
    w_lo, w_hi = float(min(corners)), float(max(corners))
    return PullOffRange(w_lo, w_hi, float(jkr_pull_off(radius, w_lo)), float(jkr_pull_off(radius, w_hi)))
