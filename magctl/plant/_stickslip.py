"""Stick-slip physics of the Mag-µBot, as plain vectorised functions of the delivered field.

Symbols (docs/plant-actuator.md):

* ``m = M·V`` magnetic moment, ``V = φ·ℓ·w·t`` (star footprint fills ``φ`` of its box).
* ``ζ = π µ a⁴ / (2 h_f)`` rotational drag of the footprint (area-equivalent disc of
  radius ``a``) turning on an oil film of thickness ``h_f`` over the glass
  (Couette flow in the film; ``µ = ν ρ`` from ``models/fluid.toml``).
* Heading: ``ζ ψ̇ = −m |B_xy| sin(ψ − ψ_B)``, time constant ``τ_ψ = ζ / (m |B_xy|)``.
* Rocking: the out-of-plane field ``b_osc sin ωt`` tips the magnet towards
  ``θ_qs = atan(b_osc / |B_xy|)``; its pitch lags as a first-order system with
  ``τ_θ = c_θ ζ / (m |B_xy|)``, so it reaches ``θ_a = θ_qs / √(1 + (ωτ_θ)²)``.
* Step per cycle: ``s = η ℓ [cos θ_0 − cos θ_a]₊`` — the body of length ``ℓ``
  pivots on an edge by ``θ_a``; below the break-away angle ``θ_0`` it sticks.
* Speed ``v = f·s``; mean tilt ``|θ|`` over a cycle ``= (2/π) θ_a``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from magctl.config import Params, load_model, require
from magctl.core.errors import ParameterError
from magctl.plant.outline import robot_outline

ROBOT_KEYS = ("magnetization", "film_gap", "pitch_drag_ratio", "break_angle", "slip_efficiency",
              "step_cv")


@dataclass(frozen=True)
class StickSlipParams:
    """Robot and fluid parameters in SI (see ``models/robot.toml`` for sources).

    Attributes
    ----------
    length, width, thickness : float
        Body ``ℓ × w × t``, m: ``ℓ`` along the heading (paper §II: 310 × 480 × 130 µm; the robot's outline,
        ``models/robot_geometry.toml``).
    footprint_area : float
        ``A``: area of the star outline, m² (``RobotOutline.area``).
    magnetization : float
        ``M``, A/m.
    film_gap : float
        ``h_f``, oil film between the robot and the glass, m.
    pitch_drag_ratio : float
        ``c_θ``: rocking drag relative to the turning drag ``ζ``.
    break_angle : float
        ``θ_0``, rad.
    slip_efficiency : float
        ``η``: fraction of the pivot geometry turned into net slip per cycle.
    step_cv : float
        Coefficient of variation of the per-frame step (0: deterministic).
    viscosity : float
        Dynamic viscosity ``µ``, Pa·s.
    """

    length: float
    width: float
    thickness: float
    footprint_area: float
    magnetization: float
    film_gap: float
    pitch_drag_ratio: float
    break_angle: float
    slip_efficiency: float
    step_cv: float
    viscosity: float

    @property
    def moment(self) -> float:
        """``m = M A t``, A·m²: the whole body is the magnetic composite."""
        return self.magnetization * self.footprint_area * self.thickness

    @property
    def disc_radius(self) -> float:
        """``a``: radius of the disc with the footprint's area, m."""
        return float(np.sqrt(self.footprint_area / np.pi))

    @property
    def turn_drag(self) -> float:
        """``ζ = π µ a⁴ / (2 h_f)``, N·m·s."""
        return np.pi * self.viscosity * self.disc_radius ** 4 / (2.0 * self.film_gap)

    def with_viscosity(self, viscosity: float) -> StickSlipParams:
        return replace(self, viscosity=float(viscosity))


def load_robot(name: str = "robot", fluid: str = "fluid") -> StickSlipParams:
    """Read ``models/<name>.toml`` ``[robot]``, the body's size and footprint area from the robot's outline
    (``robot_outline()``) and the fluid viscosity ``µ = ν ρ`` from ``models/<fluid>.toml``."""
    p = load_model(name)
    if "robot" not in p or not isinstance(p.robot, Params):
        raise ParameterError(f"{p._path}: missing [robot] table")
    require(p.robot, *ROBOT_KEYS)
    vals = {k: float(p.robot[k]) for k in ROBOT_KEYS}
    for k, v in vals.items():
        if v < 0 or (v == 0 and k not in ("step_cv", "break_angle")):
            raise ParameterError(f"{p._path}:robot.{k}: value {v!r} must be {'≥ 0' if k == 'step_cv' else '> 0'}")
    f = load_model(fluid).fluid
    require(f, "viscosity", "density")
    body = robot_outline()
    return StickSlipParams(length=body.length, width=body.width, thickness=body.thickness, footprint_area=body.area,
                           **vals, viscosity=float(f.viscosity * f.density))


def heading_rate(p: StickSlipParams, b_xy) -> np.ndarray:
    """``1/τ_ψ = m |B_xy| / ζ`` (1/s) for in-plane field magnitude ``b_xy`` (T)."""
    return p.moment * np.asarray(b_xy) / p.turn_drag


def rocking_amplitude(p: StickSlipParams, b_xy, b_osc, freq) -> np.ndarray:
    """``θ_a = atan(b_osc/|B_xy|) / √(1 + (2πf τ_θ)²)``, rad."""
    b_xy = np.maximum(np.asarray(b_xy, dtype=float), 1e-9)
    tau = p.pitch_drag_ratio * p.turn_drag / (p.moment * b_xy)
    return np.arctan(np.abs(b_osc) / b_xy) / np.sqrt(1.0 + (2.0 * np.pi * np.asarray(freq) * tau) ** 2)


def step_length(p: StickSlipParams, theta_a) -> np.ndarray:
    """``s = η ℓ [cos θ_0 − cos θ_a]₊``, m per field cycle."""
    return p.slip_efficiency * p.length * np.maximum(np.cos(p.break_angle) - np.cos(theta_a), 0.0)


def speed(p: StickSlipParams, b_xy, b_osc, freq) -> np.ndarray:
    """Mean translation speed ``v = f·s(θ_a)``, m/s."""
    freq = np.maximum(np.asarray(freq, dtype=float), 0.0)
    return freq * step_length(p, rocking_amplitude(p, b_xy, b_osc, freq))

