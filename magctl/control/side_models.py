"""The side push's models ``F`` of eq 17: the gap ``D_g`` ↔ the displacement ``D_s`` of one pass (eq 22, 23).

Everything is SI (metres). The paper prints eq 22 and eq 23 in µm; their constants are ``models/push.toml``
``[paper_side]`` (with their sources), the same forms fitted to magctl's own Fig 6 curve ``[side_fit]``. The side
push (:mod:`magctl.control.push.side`), its online law (:mod:`magctl.control.curve_learning`), the greedy assembly
planner and the analyses (:mod:`magctl.stability`) take their models from here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magctl.config import load_model
from magctl.core.errors import MagctlError
from magctl.plant.fluid.calibration import paper_side


@dataclass(frozen=True)
class ExpSideModel:
    """Eq 22: ``F(D_s) = −ln(D_s / A) / k``, i.e. ``D_s = A·exp(−k·D_g)``.

    Attributes
    ----------
    amplitude : float
        ``A`` (m); by default the paper's 1755 µm (``models/push.toml`` ``[paper_side] amplitude_um``: eq 22, fit
        of the Fig 6 simulation, R² = 0.9971).
    rate : float
        ``k`` (1/m); by default the paper's 0.009042 /µm (``[paper_side] rate_per_um``).
    """

    amplitude: float = field(default_factory=lambda: paper_side()["amplitude"])
    rate: float = field(default_factory=lambda: paper_side()["rate"])
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

    def linearised(self, gap: float, name: str = "lin") -> LinSideModel:
        """The tangent of ``F`` at the gap ``gap`` (m), as eq 23 linearises eq 22 (§VI-B).

        At ``D_s0 = A·exp(−k·gap)``: ``F_lin(D_s) = gap + 1/k − D_s/(k·D_s0)``. The paper
        says "about D_s = 500 µm", which lies in the contact region; read as the gap it gives,
        for eq 22 itself, ``−5.80·D_s + 611 µm`` beside the printed ``−5.29·D_s + 621 µm``
        (docs/push-control.md §4.2).
        """
        ds0 = float(self.displacement(gap))
        return LinSideModel(slope_=-1.0 / (self.rate * ds0), intercept=float(gap) + 1.0 / self.rate, name=name)


@dataclass(frozen=True)
class LinSideModel:
    """Eq 23: ``F_lin(D_s) = −5.29·D_s + 621 µm`` (affine; slope dimensionless).

    Attributes
    ----------
    slope_ : float
        By default the paper's −5.29 (``models/push.toml`` ``[paper_side] slope_1``: eq 23).
    intercept : float
        ``F_lin(0)`` (m); by default the paper's 621 µm (``[paper_side] intercept_um``).
    """

    slope_: float = field(default_factory=lambda: paper_side()["slope"])
    intercept: float = field(default_factory=lambda: paper_side()["intercept"])
    name: str = "lin"

    def gap(self, ds):
        return self.intercept + self.slope_ * np.asarray(ds, dtype=float)

    def displacement(self, dg):
        return (np.asarray(dg, dtype=float) - self.intercept) / self.slope_

    def slope(self, ds):
        return np.full_like(np.asarray(ds, dtype=float), self.slope_)


@dataclass(frozen=True)
class TabulatedSideModel:
    """``D_s(D_g)`` from a table (e.g. the fluid model's Fig 6 curve), log-linear between points.

    Beyond the table the end segments' exponential rates are extended. ``gap`` is the
    exact inverse and ``slope`` is ``dF/dD_s`` of the segment in use.

    Parameters
    ----------
    gaps, displacements : array_like
        Increasing gaps and the (positive, decreasing) displacements they give (m).
    """

    gaps: tuple
    displacements: tuple
    name: str = "table"

    def __post_init__(self):
        g = np.asarray(self.gaps, dtype=float)
        d = np.asarray(self.displacements, dtype=float)
        if g.ndim != 1 or g.size < 2 or g.shape != d.shape:
            raise MagctlError("side-push table needs at least two (gap, displacement) pairs of equal length")
        if np.any(np.diff(g) <= 0) or np.any(d <= 0) or np.any(np.diff(d) >= 0):
            raise MagctlError("side-push table: gaps must increase and displacements be positive and decreasing")
        object.__setattr__(self, "gaps", tuple(g))
        object.__setattr__(self, "displacements", tuple(d))

    def _tab(self):
        g = np.asarray(self.gaps)
        ld = np.log(np.asarray(self.displacements))
        return g, ld, np.diff(ld) / np.diff(g)

    def displacement(self, dg):
        g, ld, rate = self._tab()
        dg = np.asarray(dg, dtype=float)
        k = np.clip(np.searchsorted(g, dg) - 1, 0, g.size - 2)
        return np.exp(ld[k] + rate[k] * (dg - g[k]))

    def gap(self, ds):
        g, ld, rate = self._tab()
        ds = np.asarray(ds, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.log(np.where(ds > 0, ds, 1.0))
            k = np.clip(np.searchsorted(-ld, -x) - 1, 0, g.size - 2)
            return np.where(ds > 0, g[k] + (x - ld[k]) / rate[k], np.inf)

    def slope(self, ds):
        g, ld, rate = self._tab()
        ds = np.asarray(ds, dtype=float)
        k = np.clip(np.searchsorted(-ld, -np.log(ds)) - 1, 0, g.size - 2)
        return 1.0 / (rate[k] * ds)


SIDE_MODELS = {
    "lin": "eq 23 as printed (fitted to the paper's Fig 6 simulation)",
    "exp": "eq 22 as printed (fitted to the paper's Fig 6 simulation)",
    "lin-fit": "eq 23's form refitted to magctl's Fig 6 curve (models/push.toml [side_fit])",
    "exp-fit": "eq 22's form refitted to magctl's Fig 6 curve (models/push.toml [side_fit])",
}
"""The side-push models by name: the paper's eq 22/23 and the same forms fitted to magctl's plant."""


def fitted_side_model() -> ExpSideModel:
    """Eq 22's form fitted to magctl's own Fig 6 curve, as the paper fitted its simulation (§VI-B).

    ``A`` and ``k`` come from ``models/push.toml`` ``[side_fit]``, which the ``sidepush-curve``
    study regenerates (and a test checks against it).
    """
    fit = load_model("push").side_fit
    return ExpSideModel(amplitude=float(fit.amplitude), rate=float(fit.rate), name="exp-fit")


def side_model(name: str):
    """A model of :data:`SIDE_MODELS`: ``"exp"`` → eq 22, ``"lin"`` → eq 23 (as printed);
    ``"exp-fit"`` / ``"lin-fit"`` → the same forms fitted to magctl's Fig 6 curve, the linear one
    the tangent of the exponential at ``[side_fit] about_gap`` (as eq 23 linearises eq 22)."""
    if name == "exp":
        return ExpSideModel()
    if name == "lin":
        return LinSideModel()
    if name == "exp-fit":
        return fitted_side_model()
    if name == "lin-fit":
        return fitted_side_model().linearised(float(load_model("push").side_fit.about_gap), name="lin-fit")
    raise MagctlError(f"side-push model {name!r} is not known; use one of {', '.join(SIDE_MODELS)}")


__all__ = ["SIDE_MODELS", "ExpSideModel", "LinSideModel", "TabulatedSideModel", "fitted_side_model", "paper_side",
           "side_model"]
