"""How one straight robot pass moves every sphere on the slide: the pass map of ``models/pass_map.toml``.

A pass drives the robot from ``a`` to ``b``. In the pass frame (``u`` along ``b − a``, ``n`` = ``u``
turned +90°) sphere ``i`` sits at ``ξ_i = (P_i − a)·u`` along and ``h_i = (P_i − a)·n`` across; the robot
goes from ``−ξ_i`` to ``L − ξ_i`` relative to it (``L = |b − a|``), so the pass moves it by

    ΔP_i = [S_a(L − ξ_i, |h_i|) − S_a(−ξ_i, |h_i|)]·u + sign(h_i)·[S_w(L − ξ_i, |h_i|) − S_w(−ξ_i, |h_i|)]·n

with ``S_a``, ``S_w`` the cumulative displacement along the motion and away from the line that
:mod:`magctl.studies.pass_map` identified from the sphere block (Fig 6 is ``S_a(1 mm, h) − S_a(−1 mm, h)``).
The map is one cubic B-spline with the two components as its outputs (a casadi interpolant, so each point's
basis is found once for both), and the same expression evaluates numerically and, with casadi symbols, gives
the assembly planner exact gradients.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from magctl.config import load_model
from magctl.core.errors import MagctlError
from magctl.core.units import MM

SMOOTH_GAP = 1e-6
"""``|h|`` is taken as ``√(h² + η²)`` with η = 1 µm so the prediction is smooth where a line crosses a sphere."""


@dataclass(frozen=True)
class PassMap:
    """The identified pass map (metres).

    Attributes
    ----------
    positions : (X,) array
        Robot position along its line relative to the sphere.
    gaps : (G,) array
        Side gap ``|h|`` from the line to the sphere centre.
    along, away : (X, G) arrays
        ``S_a``, ``S_w``: displacement since the robot was at ``positions[0]``.
    min_gap : float
        The contact threshold the map was identified with (passes keep at least this from every sphere); the
        map's gaps start there and a sphere nearer a line — beyond the end of its pass — reads the first gap.
    """

    positions: np.ndarray
    gaps: np.ndarray
    along: np.ndarray
    away: np.ndarray
    min_gap: float

    @classmethod
    def load(cls, name: str = "pass_map") -> PassMap:
        """Read ``models/<name>.toml`` (written by :func:`magctl.studies.pass_map.write_model`)."""
        p = load_model(name)
        m = p.map
        x, g = np.asarray(m.positions, float), np.asarray(m.gaps, float)
        shape = (x.size, g.size)
        try:
            along, away = np.asarray(m.along, float).reshape(shape), np.asarray(m.away, float).reshape(shape)
        except ValueError as exc:
            raise MagctlError(f"models/{name}.toml: along/away need {x.size} x {g.size} values") from exc
        return cls(x, g, along, away, float(p.provenance.min_gap))

    def __post_init__(self):
        if np.any(np.diff(self.positions) <= 0) or np.any(np.diff(self.gaps) <= 0):
            raise MagctlError("pass map: positions and gaps must increase")
        for a in (self.along, self.away):
            if a.shape != (self.positions.size, self.gaps.size) or not np.all(np.isfinite(a)):
                raise MagctlError("pass map: along and away must be finite, positions x gaps")

    @cached_property
    def _spline(self) -> ca.Function:
        """``(S_a, S_w)`` as one casadi B-spline of ``(x, |h|)`` in mm, values in mm (the same values as a spline
        per component: the outputs share the basis, which is most of the work of an evaluation)."""
        grid = [self.positions / MM, self.gaps / MM]
        values = np.stack([(table / MM).ravel(order="F") for table in (self.along, self.away)], axis=-1)
        return ca.interpolant("S_pass", "bspline", grid, values.ravel())

    def _clamped(self, x, h):
        """Positions beyond the map read its ends (the sphere has not yet moved / has stopped moving); gaps
        below its first (the contact threshold: only spheres beyond the pass's end) read the first."""
        lo, hi = self.positions[[0, -1]] / MM
        return ca.fmin(ca.fmax(x, lo), hi), ca.fmin(ca.fmax(h, self.gaps[0] / MM), self.gaps[-1] / MM)

    def symbolic(self, spheres, a, b):
        """ΔP (N × 2, mm) of spheres ``(N, 2)`` for the pass ``a → b`` (mm); casadi or numeric entries."""
        spline = self._spline
        d = b - a
        length = ca.sqrt(ca.sumsqr(d))
        u = d / length
        n = ca.vertcat(-u[1], u[0])
        rows = []
        for i in range(spheres.shape[0]):
            rel = spheres[i, :].T - a
            xi, h = ca.dot(rel, u), ca.dot(rel, n)
            hh = ca.sqrt(h ** 2 + (SMOOTH_GAP / MM) ** 2)
            x1, hc = self._clamped(length - xi, hh)
            x0, _ = self._clamped(-xi, hh)
            moved = spline(ca.vertcat(x1, hc)) - spline(ca.vertcat(x0, hc))
            rows.append((moved[0] * u + moved[1] * h / hh * n).T)
        return ca.vertcat(*rows)

    @cached_property
    def _numeric(self) -> dict[int, ca.Function]:
        return {}

    def displacement(self, spheres, a, b) -> np.ndarray:
        """ΔP (N, 2) in metres of spheres ``(N, 2)`` for the pass from ``a`` to ``b`` (m)."""
        spheres = np.asarray(spheres, float).reshape(-1, 2)
        n = spheres.shape[0]
        f = self._numeric.get(n)
        if f is None:
            p, a_, b_ = ca.MX.sym("p", n, 2), ca.MX.sym("a", 2), ca.MX.sym("b", 2)
            f = self._numeric[n] = ca.Function("pass_displacement", [p, a_, b_], [self.symbolic(p, a_, b_)])
        out = f(spheres / MM, np.asarray(a, float) / MM, np.asarray(b, float) / MM)
        return np.asarray(out, float).reshape(n, 2) * MM

    def side_curve(self, gaps, behind: float = 1e-3, ahead: float = 1e-3) -> np.ndarray:
        """Fig 6 read from the map: displacement along a pass from ``behind`` to ``ahead`` at ``gaps`` (m)."""
        out = []
        for g in np.atleast_1d(np.asarray(gaps, float)):
            d = self.displacement(np.array([[0.0, g]]), np.array([-behind, 0.0]), np.array([ahead, 0.0]))
            out.append(d[0, 0])
        return np.asarray(out)


def pass_map() -> PassMap:
    """The pass map of ``models/pass_map.toml``."""
    return PassMap.load()


__all__ = ["PassMap", "pass_map"]
