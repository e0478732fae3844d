"""Shared pieces of the push tasks: side-push models (eq 22, 23), status codes, geometry.

Everything is SI (metres). The paper writes eq 22 and eq 23 in µm; the
constants below are theirs, converted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl.core.errors import MagctlError

UM = 1e-6

# --- task status codes (the ``status`` port) ---------------------------------------------------
RUNNING = 0
CONVERGED = 1
ATTEMPT_LIMIT = 2
TRACKING_LOST = 3
SPHERE_LOST = 4
STATUS_NAMES = {RUNNING: "running", CONVERGED: "converged", ATTEMPT_LIMIT: "attempt_limit",
                TRACKING_LOST: "tracking_lost", SPHERE_LOST: "sphere_lost"}


# --- side-push models: gap D_g ↔ displacement D_s -----------------------------------------------
@dataclass(frozen=True)
class ExpSideModel:
    """Eq 22: ``F(D_s) = −ln(D_s / A) / k``, i.e. ``D_s = A·exp(−k·D_g)``.

    Attributes
    ----------
    amplitude : float
        ``A`` = 1755 µm (paper eq 22, fit of the Fig 6 simulation, R² = 0.9971).
    rate : float
        ``k`` = 0.009042 /µm (paper eq 22).
    """

    amplitude: float = 1755 * UM
    rate: float = 0.009042 / UM
    name: str = "exp"

    def gap(self, ds):
        """``F(D_s)``: the gap that gives displacement ``D_s`` (m); ``D_s`` ≤ 0 maps to an infinite gap."""
        ds = np.asarray(ds, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(ds > 0, -np.log(np.where(ds > 0, ds, 1.0) / self.amplitude) / self.rate, np.inf)

    def displacement(self, dg):
        """``F⁻¹(D_g)``: displacement of a sphere passed at gap ``D_g`` (m)."""
        return self.amplitude * np.exp(-self.rate * np.asarray(dg, dtype=float))

    def slope(self, ds):
        """``dF/dD_s = −1/(k·D_s)``."""
        return -1.0 / (self.rate * np.asarray(ds, dtype=float))


@dataclass(frozen=True)
class LinSideModel:
    """Eq 23: ``F_lin(D_s) = −5.29·D_s + 621 µm`` (affine; slope dimensionless).

    Attributes
    ----------
    slope_ : float
        −5.29 (paper eq 23).
    intercept : float
        621 µm (paper eq 23).
    """

    slope_: float = -5.29
    intercept: float = 621 * UM
    name: str = "lin"

    def gap(self, ds):
        return self.intercept + self.slope_ * np.asarray(ds, dtype=float)

    def displacement(self, dg):
        return (np.asarray(dg, dtype=float) - self.intercept) / self.slope_

    def slope(self, ds):
        return np.full_like(np.asarray(ds, dtype=float), self.slope_)


def side_model(name: str):
    """``"exp"`` → eq 22, ``"lin"`` → eq 23."""
    if name == "exp":
        return ExpSideModel()
    if name == "lin":
        return LinSideModel()
    raise MagctlError(f"side-push model {name!r} is not known; use 'lin' (eq 23) or 'exp' (eq 22)")


# --- small batched geometry helpers ------------------------------------------------------------
def norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def unit(v: np.ndarray, fallback=(1.0, 0.0)) -> np.ndarray:
    """Unit vectors along the last axis (``fallback`` where the vector is zero)."""
    n = norm(v)[..., None]
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), np.asarray(fallback, dtype=float))


def perp(v: np.ndarray) -> np.ndarray:
    """``v`` rotated by +90°."""
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def check_positive(name: str, value: float, allow_zero: bool = False) -> float:
    """``value`` as a float, or a :class:`MagctlError` naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise MagctlError(f"{name}={value!r} is not a number") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise MagctlError(f"{name}={value!r} must be {'non-negative' if allow_zero else 'positive'} and finite")
    return v
