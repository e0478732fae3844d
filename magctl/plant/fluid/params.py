"""Fluid and sphere parameters from ``models/`` in SI."""

from __future__ import annotations

import math
from dataclasses import dataclass

from magctl.config import load_model
from magctl.core.errors import ParameterError

GRAVITY = 9.80665
"""Standard gravity [m/s²]."""


def fluid_viscosity(fluid=None) -> float:
    """Dynamic viscosity μ = ν ρ [Pa·s] from ``models/fluid.toml``."""
    f = (fluid if fluid is not None else load_model("fluid")).fluid
    mu = f.viscosity * f.density
    if mu <= 0:
        raise ParameterError(f"fluid viscosity {f.viscosity!r} m^2/s and density {f.density!r} kg/m^3 must be positive")
    return float(mu)


def fluid_density(fluid=None) -> float:
    """Fluid density [kg/m³] from ``models/fluid.toml``."""
    return float((fluid if fluid is not None else load_model("fluid")).fluid.density)


@dataclass(frozen=True)
class SphereParams:
    """The sphere table of ``models/sphere.toml`` in SI (see that file for sources)."""

    radius: float
    density: float
    roughness: float
    adhesion_range: float
    adhesion: bool
    drag_mode: str
    substeps: int
    contact_tolerance: float
    sticky_probability: float
    sticky_mobility: float
    release_scatter: float
    contact_gap: float
    film_cutoff: float
    edge_coefficient: float
    edge_cutoff: float
    mobility: float = 1.0


def sphere_params(p=None) -> SphereParams:
    """Load and check ``models/sphere.toml``."""
    p = p if p is not None else load_model("sphere")
    s, v, c = p.sphere, p.variability, p.contact
    out = SphereParams(s.radius, s.density, s.roughness, s.adhesion_range, bool(s.adhesion), str(s.drag_mode),
                       int(s.substeps), s.contact_tolerance, v.sticky_probability, v.sticky_mobility,
                       v.release_scatter, c.robot_gap, c.film_cutoff, c.edge_law, c.edge_law_cutoff, v.mobility)
    if out.radius <= 0 or out.roughness <= 0:
        raise ParameterError(f"{p._path}: sphere radius and roughness must be positive")
    if min(out.contact_gap, out.film_cutoff, out.edge_coefficient, out.edge_cutoff) <= 0:
        raise ParameterError(f"{p._path}: contact.robot_gap, film_cutoff, edge_law, edge_law_cutoff must be > 0")
    if out.drag_mode not in ("paper", "accurate"):
        raise ParameterError(f"{p._path}: sphere.drag_mode must be 'paper' or 'accurate', got {out.drag_mode!r}")
    if out.substeps < 1:
        raise ParameterError(f"{p._path}: sphere.substeps_count must be >= 1")
    if not (math.isfinite(out.mobility) and out.mobility > 0):
        raise ParameterError(f"{p._path}: variability.mobility_ratio must be a finite number > 0, got {out.mobility!r}")
    if not 0 <= out.sticky_probability <= 1:
        raise ParameterError(f"{p._path}: variability.sticky_probability_ratio must lie in [0, 1]")
    return out
