"""Side-push curve identification (paper §IV-D Fig 6, §VI-B eq 22-23): logged side passes → eq 22 and the plant.

Each logged side pass gives the achieved gap ``D_g`` (sphere centre to the robot's path line, m), the sphere's
net displacement ``D_s`` (m) and the group (sphere / run) it belongs to. Two fits are made to them:

* **eq 22** (:func:`fit_eq22`): ``D_s = a·exp(−b·D_g)`` by least squares on ``ln D_s`` — the fit of
  :func:`magctl.plant.fluid.scenarios.sidepush_fit`, with standard uncertainties from that regression's
  covariance — → ``models/push.toml [side_fit]`` ``amplitude_um`` (a) and ``rate_per_um`` (b), the curve the
  side-push models "exp-fit" and "lin-fit" use (eq 23 is its tangent at ``about_gap_um``, which is a setting,
  not a fit output, and is not written).
* **the physical plant** (:func:`fit_plant`): the depth ``H`` of the oil layer under its lid
  (``models/fluid.toml [domain] depth_mm``) and the mean sphere mobility multiplier ``m``
  (``models/sphere.toml [variability] mobility_ratio``), by nonlinear least squares on ``ln D_s`` through the
  flow solver's side-push curve ``D_s(D_g; H, m)`` (:func:`magctl.plant.fluid.scenarios.pass_profile`, the
  lid domain) computed on the grid of ``models/identify.toml [side]`` and interpolated
  (:class:`SidePushModel`; one flow solve per grid depth, cached in memory and on disk).

:func:`fit_side` makes both and returns a :class:`SideFit` whose :meth:`SideFit.estimates` are the
:class:`~magctl.identify.estimate.Estimate` s of the four values. Lengths are SI (m) throughout; the estimates are
in their keys' units (µm, 1/µm, mm, ratio).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from magctl.config import load_model
from magctl.core.errors import ParameterError
from magctl.identify.estimate import Estimate, IdentifyError, NotIdentified
from magctl.plant.fluid.params import SphereParams, sphere_params
from magctl.plant.fluid.scenarios import APPROACH, ROBOT_SPEED, pass_profile, sidepush_fit

GAP_RESOLUTION = 1e-6
"""Gaps closer than this count as the same gap when counting distinct gaps [m] (1 µm, well under a 7.5 µm pixel)."""

_UM, _MM = 1e-6, 1e-3


# --- the grid and the flow solver's curves on it ---------------------------------------------------------------------

@dataclass(frozen=True)
class SideGrid:
    """Where the flow solver's side-push curve is computed (``models/identify.toml [side]``).

    Attributes
    ----------
    depths : tuple of float
        Lid depths ``H`` [m] (one flow solve each).
    mobilities : tuple of float
        Mean sphere mobility multipliers ``m`` [1].
    gaps : tuple of float
        Side gaps ``D_g`` [m]; passes outside ``[gaps[0], gaps[-1]]`` are left out of the plant fit.
    """

    depths: tuple[float, ...]
    mobilities: tuple[float, ...]
    gaps: tuple[float, ...]

    def __post_init__(self):
        for name in ("depths", "mobilities", "gaps"):
            v = np.asarray(getattr(self, name), float)
            if v.ndim != 1 or len(v) < 4 or not np.all(np.isfinite(v)) or np.any(v <= 0) or np.any(np.diff(v) <= 0):
                raise ParameterError(f"side grid: {name} must be >= 4 increasing positive values, got {v.tolist()}")

    @classmethod
    def from_params(cls, p=None) -> SideGrid:
        """From ``models/identify.toml [side]`` (``p``: a loaded ``identify`` model, by default the file's)."""
        p = p if p is not None else load_model("identify")
        s = p.side
        lo, hi = (float(x) for x in np.asarray(s.gap_range, float).ravel()[:2])
        step = float(s.gap_step)
        if not (0 < lo < hi and step > 0):
            raise ParameterError(f"{p._path}: side.gap_range_um must be [low, high] with 0 < low < high, "
                                 f"gap_step_um > 0")
        n = int(round((hi - lo) / step))
        gaps = lo + (hi - lo) * np.arange(n + 1) / n
        return cls(tuple(float(x) for x in np.asarray(s.depth_grid, float)),
                   tuple(float(x) for x in np.asarray(s.mobility_grid, float)), tuple(float(x) for x in gaps))

    def describe(self) -> str:
        """``lid depth 0.75-1.35 mm × mobility 0.2-2.25 × D_g 300-700 µm`` with the point counts."""
        d, m, g = self.depths, self.mobilities, self.gaps
        return (f"lid depth {d[0] / _MM:g}-{d[-1] / _MM:g} mm ({len(d)}) × mobility {m[0]:g}-{m[-1]:g} ({len(m)}) "
                f"× D_g {g[0] / _UM:.0f}-{g[-1] / _UM:.0f} µm ({len(g)})")


class SidePushModel:
    """The flow solver's side-push displacement ``D_s(D_g; H, m)`` on a :class:`SideGrid`, interpolated.

    For every grid depth ``H`` (oil under a no-slip lid, :class:`~magctl.plant.fluid.domain.Domain` ``"lid"``) and
    mobility ``m`` (:attr:`SphereParams.mobility`), :func:`~magctl.plant.fluid.scenarios.pass_profile` gives
    the displacement's components along the robot's motion and away from its line at every grid gap. Those
    divided by ``m`` vary slowly and smoothly (``D_s`` is ``m`` times the flow's drift to first order) and are
    interpolated cubically in ``(H, ln m, D_g)``; ``D_s`` is ``m`` times the norm of the two. Interpolating the
    components rather than ``ln D_s`` keeps the model smooth where a shallow layer's along-component changes
    sign (the oil returning under the lid, ~600 µm at 0.75 mm) and ``ln D_s`` has a cusp.

    Parameters
    ----------
    grid : SideGrid
    speed, travel : float
        The passes' robot speed [m/s] and start/end distance from the sphere along the path [m]
        (the paper's 0.4 mm/s and 1 mm, ``models/push.toml [side]``).
    start : float, optional
        The displacement counts from the robot at ``start`` behind the sphere (``models/identify.toml [side]
        fix_start_um``, where :func:`magctl.identify.phases.side_passes` takes a logged pass's first fix); the
        whole pass (``travel``) by default.
    sphere : SphereParams, optional
        The sphere model (``models/sphere.toml``); its ``mobility`` is replaced by each grid value.
    """

    def __init__(self, grid: SideGrid, speed: float = ROBOT_SPEED, travel: float = APPROACH,
                 sphere: SphereParams | None = None, start: float | None = None):
        from scipy.interpolate import RegularGridInterpolator

        from magctl.plant.fluid.domain import Domain

        self.grid, self.speed, self.travel = grid, float(speed), float(travel)
        self.start = self.travel if start is None else min(float(start), self.travel)
        sphere = sphere if sphere is not None else sphere_params()
        gaps = np.asarray(grid.gaps)
        shape = (len(grid.depths), len(grid.mobilities), len(gaps))
        along, away = np.empty(shape), np.empty(shape)
        for i, depth in enumerate(grid.depths):
            domain = Domain("lid", depth)
            for j, m in enumerate(grid.mobilities):
                prof = pass_profile(gaps, reach=self.travel, speed=self.speed, domain=domain,
                                    params=dataclasses.replace(sphere, mobility=m))
                # from the robot at −start (where a logged pass's first fix is taken) to the pass's end
                k = int(np.searchsorted(prof.positions, -self.start))
                a0 = prof.along[k - 1] if k > 0 else 0.0
                w0 = prof.away[k - 1] if k > 0 else 0.0
                along[i, j], away[i, j] = (prof.along[-1] - a0) / m, (prof.away[-1] - w0) / m
        self.along, self.away = along, away
        axes = (np.asarray(grid.depths) / _MM, np.log(grid.mobilities), gaps / _UM)
        self._along = RegularGridInterpolator(axes, along / _UM, method="cubic")
        self._away = RegularGridInterpolator(axes, away / _UM, method="cubic")
        self.log_mobility_bounds = (math.log(grid.mobilities[0]), math.log(grid.mobilities[-1]))

    def contains(self, gaps) -> np.ndarray:
        """Which gaps [m] lie within the grid's gap range."""
        g = np.asarray(gaps, float)
        return (g >= self.grid.gaps[0]) & (g <= self.grid.gaps[-1])

    def log_displacement(self, depth: float, log_mobility: float, gaps) -> np.ndarray:
        """``ln D_s`` [ln m] at lid depth ``depth`` [m], ``ln m`` and gaps [m] within the grid."""
        g = np.asarray(gaps, float) / _UM
        pts = np.column_stack([np.full(g.shape, depth / _MM), np.full(g.shape, log_mobility), g])
        return log_mobility + np.log(np.hypot(self._along(pts), self._away(pts)) * _UM)

    def displacement(self, depth: float, mobility: float, gaps) -> np.ndarray:
        """``D_s`` [m] at lid depth [m], mean mobility and gaps [m]; NaN outside the grid's gap range."""
        g = np.asarray(gaps, float)
        out = np.full(g.shape, np.nan)
        ok = self.contains(g)
        out[ok] = np.exp(self.log_displacement(depth, math.log(mobility), g[ok]))
        return out


_MODELS: dict[tuple, SidePushModel] = {}


def side_model(grid: SideGrid | None = None, speed: float = ROBOT_SPEED, travel: float = APPROACH,
               sphere: SphereParams | None = None, start: float | None = None) -> SidePushModel:
    """The :class:`SidePushModel` for this grid (``models/identify.toml [side]`` by default), built once per
    process: a new grid depth costs one flow solve (~15 s, then cached on disk under ``$MAGCTL_CACHE``), every
    (depth, mobility) one batched side-push simulation (~5 ms)."""
    grid = grid if grid is not None else SideGrid.from_params()
    sphere = sphere if sphere is not None else sphere_params()
    start = fix_start() if start is None else float(start)
    key = (grid, float(speed), float(travel), sphere, start)
    model = _MODELS.get(key)
    if model is None:
        model = _MODELS[key] = SidePushModel(grid, speed, travel, sphere, start)
    return model


def fix_start(p=None) -> float:
    """How far behind the sphere [m] the robot is when a logged pass's first fix is taken
    (``models/identify.toml [side] fix_start_um``)."""
    return float((p if p is not None else load_model("identify")).side.fix_start)


# --- the passes ------------------------------------------------------------------------------------------------------

def _distinct(gaps) -> int:
    return len(np.unique(np.round(np.asarray(gaps, float) / GAP_RESOLUTION)))


def _passes(gaps, displacement, group=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The usable passes (finite, ``D_g > 0``, ``D_s > 0``) and how many were dropped."""
    g = np.atleast_1d(np.asarray(gaps, float)).ravel()
    d = np.atleast_1d(np.asarray(displacement, float)).ravel()
    grp = np.zeros(len(g), np.int64) if group is None else np.atleast_1d(np.asarray(group)).ravel()
    if not (len(g) == len(d) == len(grp)):
        raise IdentifyError(f"side passes: {len(g)} gaps, {len(d)} displacements and {len(grp)} group ids "
                            "must be as many")
    if grp.dtype.kind not in "iub":
        if grp.dtype.kind == "f" and np.all(np.isfinite(grp)) and np.all(grp == np.round(grp)):
            grp = grp.astype(np.int64)
        else:
            raise IdentifyError(f"side passes: group ids must be integers, got dtype {grp.dtype}")
    ok = np.isfinite(g) & np.isfinite(d) & (g > 0) & (d > 0)
    return g[ok], d[ok], grp[ok].astype(np.int64), int((~ok).sum())


def _span(g) -> str:
    return f"{np.min(g) / _UM:.0f}-{np.max(g) / _UM:.0f} µm"


# --- eq 22 -----------------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Eq22Fit:
    """Eq 22's form ``D_s = a·exp(−b·D_g)`` fitted by least squares on ``ln D_s``.

    Attributes
    ----------
    amplitude : float
        ``a`` [m] (paper eq 22: 1755 µm).
    rate : float
        ``b`` [1/m] (paper eq 22: 0.009042 /µm).
    cov : ndarray (2, 2)
        Covariance of ``(ln a, b)`` [1, 1/m] from the regression: ``s² (XᵀX)⁻¹``, ``s²`` the residual variance
        of ``ln D_s`` on ``n − 2`` degrees of freedom.
    r2 : float
        R² of the fitted curve on ``D_s`` itself (as :func:`~magctl.plant.fluid.scenarios.sidepush_fit`).
    log_sd : float
        Residual standard deviation of ``ln D_s`` (``s``, a relative scatter of D_s).
    passes, gaps : int
        Passes fitted and distinct gaps among them.
    gap_range : tuple of float
        Smallest and largest gap fitted [m].
    """

    amplitude: float
    rate: float
    cov: np.ndarray = field(repr=False)
    r2: float
    log_sd: float
    passes: int
    gaps: int
    gap_range: tuple[float, float]

    @property
    def amplitude_sd(self) -> float:
        """Standard uncertainty of ``a`` [m] (``a·σ(ln a)``)."""
        return self.amplitude * math.sqrt(self.cov[0, 0])

    @property
    def rate_sd(self) -> float:
        """Standard uncertainty of ``b`` [1/m]."""
        return math.sqrt(self.cov[1, 1])

    def predict(self, gaps) -> np.ndarray:
        """Eq 22: ``D_s = a·exp(−b·D_g)`` [m] at gaps [m]."""
        return self.amplitude * np.exp(-self.rate * np.asarray(gaps, float))

    def describe(self) -> str:
        return (f"eq 22 D_s = a·exp(−b·D_g) by least squares on ln D_s over {self.passes} side passes at "
                f"{self.gaps} gaps {self.gap_range[0] / _UM:.0f}-{self.gap_range[1] / _UM:.0f} µm, "
                f"R² = {self.r2:.4f} (on D_s), log residual sd {self.log_sd:.3f}, "
                f"corr(ln a, b) = {self.cov[0, 1] / math.sqrt(self.cov[0, 0] * self.cov[1, 1] or 1.0):+.3f}")


def fit_eq22(gaps, displacement) -> Eq22Fit:
    """Fit eq 22's form ``D_s = a·exp(−b·D_g)`` to side passes (gaps and displacements in m).

    ``ln a`` and ``b`` come from :func:`~magctl.plant.fluid.scenarios.sidepush_fit` (least squares of
    ``ln D_s = ln a − b·D_g``); their covariance is the regression's, ``s² (XᵀX)⁻¹`` about the mean gap
    ``ḡ``: ``var b = s²/Σ(g−ḡ)²``, ``var ln a = s²/n + ḡ² var b``, ``cov(ln a, b) = ḡ var b``. Passes with
    ``D_s ≤ 0`` or non-finite values are ignored.

    Raises
    ------
    NotIdentified
        Fewer than 3 usable passes or fewer than 2 distinct gaps among them.
    """
    g, d, _, _ = _passes(gaps, displacement)
    n, k = len(g), _distinct(g)
    if n < 3 or k < 2:
        raise NotIdentified(f"eq 22 fit needs >= 3 side passes with D_s > 0 at >= 2 distinct gaps, got {n} "
                            f"at {k}")
    a, b, r2 = sidepush_fit(g, d)
    resid = np.log(d) - (math.log(a) - b * g)
    s2 = float(resid @ resid) / (n - 2) if n > 2 else 0.0
    gbar = float(g.mean())
    var_b = s2 / float(np.sum((g - gbar) ** 2))
    cov = np.array([[s2 / n + gbar**2 * var_b, gbar * var_b], [gbar * var_b, var_b]])
    return Eq22Fit(a, b, cov, float(r2), math.sqrt(s2), n, k, (float(g.min()), float(g.max())))


# --- the plant: oil depth and mean sphere mobility -------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class PlantFit:
    """The plant's lid depth ``H`` and mean sphere mobility ``m`` fitted to side passes through the flow solver.

    Attributes
    ----------
    depth, depth_sd : float
        ``H`` and its standard uncertainty [m].
    mobility, mobility_sd : float
        The mean mobility multiplier (``models/sphere.toml mobility_ratio``, the arithmetic mean the plant's
        mean-one lognormal scatter multiplies: ``exp(ln m̂ + σ_b²/2)``) and its standard uncertainty [1].
    log_mobility, log_mobility_sd : float
        ``ln m̂`` of the pooled fit (the passes' typical sphere: a geometric mean) and its uncertainty from the
        fit alone.
    mobility_log_sd : float
        Total uncertainty of ``ln m`` (the fit's and the between-sphere scatter's, see :func:`fit_plant`).
    between_log_sd : float
        ``σ_b``, the between-sphere scatter of ``ln m``: the spread of the groups' mobilities, or the model's
        release scatter when there is only one group.
    between_source : str
        ``"groups"`` or ``"model"``.
    group_mobility : dict of int to float
        Each group's mobility at the fitted depth (several groups only; empty otherwise).
    correlation : float
        Correlation of ``H`` and ``ln m`` in the fit.
    log_sd, r2 : float
        Residual standard deviation and R² of ``ln D_s``.
    passes, gaps, groups, outside : int
        Passes fitted, distinct gaps, groups among them, and passes left out for lying outside the grid's gaps.
    model : SidePushModel
    """

    depth: float
    depth_sd: float
    mobility: float
    mobility_sd: float
    log_mobility: float
    log_mobility_sd: float
    mobility_log_sd: float
    between_log_sd: float
    between_source: str
    group_mobility: dict
    correlation: float
    log_sd: float
    r2: float
    passes: int
    gaps: int
    groups: int
    outside: int
    model: SidePushModel = field(repr=False, compare=False)

    def predict(self, gaps) -> np.ndarray:
        """The fitted plant's ``D_s`` [m] at gaps [m] (the typical sphere, ``m̂``); NaN outside the grid's gaps."""
        return self.model.displacement(self.depth, math.exp(self.log_mobility), gaps)

    def describe(self) -> str:
        grid = self.model.grid
        text = (f"the flow solver's side-push curve (oil under a lid; grid {grid.describe()}, cubic interpolation) "
                f"fitted by least squares on ln D_s over {self.passes} side passes at {self.gaps} gaps")
        if self.outside:
            text += f" ({self.outside} outside the grid's gaps left out)"
        text += (f", log residual sd {self.log_sd:.3f}, R² = {self.r2:.4f} (ln D_s), "
                 f"corr(depth, ln mobility) = {self.correlation:+.2f}")
        return text

    def mobility_note(self) -> str:
        if self.between_source == "model":
            return (f"all passes of one sphere (group): the between-sphere scatter is not observed, taken as the "
                    f"model's release scatter (models/rig.toml [physics], σ(ln m) = {self.between_log_sd:.3f}) and "
                    f"added to the fit's {self.log_mobility_sd:.3f}")
        spread = ", ".join(f"{k}: {v:.3g}" for k, v in self.group_mobility.items())
        return (f"{self.groups} spheres (groups) with mobilities {spread} at the fitted depth: "
                f"σ(ln m) between them {self.between_log_sd:.3f}, uncertainty of the mean the larger of "
                f"{self.between_log_sd:.3f}/√{self.groups} and the fit's {self.log_mobility_sd:.3f}")


def pass_noise(p=None) -> tuple[float, float]:
    """(σ_abs [m], σ_rel) of a logged pass's displacement (``models/identify.toml [side]``): the weights of the
    plant fit, ``1/√(σ_rel² + (σ_abs/D_s)²)`` on ``ln D_s``."""
    s = (p if p is not None else load_model("identify")).side
    return float(s.displacement_noise), float(s.relative_noise)


def _release_log_sd() -> float:
    """σ of ln m of the model's lognormal mobility scatter (``models/rig.toml [physics] release_scatter_ratio``)."""
    rs = float(load_model("rig").physics.release_scatter)
    return math.sqrt(math.log1p(rs**2))


def _at_edge(x: float, lo: float, hi: float) -> bool:
    return min(x - lo, hi - x) <= 1e-4 * (hi - lo)


def measured(log_displacement, fix_noise: float) -> np.ndarray:
    """``ln`` of the displacement a log measures when the sphere moved ``exp(log_displacement)`` [m]: the length
    of the difference of two fixes, each with noise ``fix_noise`` [m] per axis, is biased up,
    ``E|d|² = D_s² + 4σ²`` — a few µm that dominate the passes far from the robot."""
    return 0.5 * np.log(np.exp(2.0 * np.asarray(log_displacement)) + 4.0 * fix_noise**2)


def fit_plant(gaps, displacement, group=None, model: SidePushModel | None = None,
              fix_noise: float = 0.0) -> PlantFit:
    """Fit the plant's lid depth ``H`` and mean sphere mobility ``m`` to side passes (gaps, displacements in m).

    Minimises ``Σ w² (ln D_s,model(D_g; H, ln m) − ln D_s)²`` (weights ``w`` of :func:`pass_noise`) over the
    passes within the grid's gaps
    (scipy ``least_squares`` within the grid, started from the best grid node), ``D_s,model`` the flow solver's
    side-push curve interpolated (:class:`SidePushModel`; eq 22 is this curve's exponential fit). The
    covariance of ``(H, ln m)`` is ``s² (JᵀJ)⁻¹``, ``J`` the weighted Jacobian at the optimum and ``s²`` the
    weighted residual variance on ``n − 2`` degrees of freedom (the weights set the passes' relative precision,
    the data their overall scale).

    The oil depth is shared by every sphere; the mobility is each sphere's own. The estimate is of the mean
    over spheres: with one group (sphere) only, the between-sphere scatter ``σ_b`` is the model's release
    scatter and adds to the fit's uncertainty of ``ln m`` in quadrature (``σ_b/√1``); with several, each group's
    ``ln m_g`` is fitted at the pooled depth, ``σ_b`` is their standard deviation, and the uncertainty of the
    mean is the larger of ``σ_b/√n_groups`` and the fit's. The reported mean is ``exp(ln m̂ + σ_b²/2)``.

    Raises
    ------
    NotIdentified
        Fewer than 4 passes or 3 distinct gaps within the grid's gaps; an optimum (or a group's mobility) on
        the grid's edge; passes that do not separate depth from mobility.
    """
    from scipy.optimize import least_squares

    model = model if model is not None else side_model()
    g, d, grp, _ = _passes(gaps, displacement, group)
    inside = model.contains(g)
    outside = int((~inside).sum())
    g, d, grp = g[inside], d[inside], grp[inside]
    n, k = len(g), _distinct(g)
    grid = model.grid
    if n < 4 or k < 3:
        raise NotIdentified(f"oil depth and sphere mobility need >= 4 side passes at >= 3 distinct gaps within "
                            f"{grid.gaps[0] / _UM:.0f}-{grid.gaps[-1] / _UM:.0f} µm, got {n} at {k}"
                            + (f" ({outside} outside)" if outside else ""))
    y = np.log(d)
    # var(ln D_s) = σ_rel² + (σ_abs/D_s)²: a pass's scatter is relative where D_s is large and the tracker's and
    # the sphere's settling's few µm where it is small; D_s from eq 22's smooth fit, not the noisy pass itself
    s_abs, s_rel = pass_noise()
    d_smooth = np.exp(np.polyval(np.polyfit(g, y, 1), g))
    w = 1.0 / np.sqrt(s_rel**2 + (s_abs / d_smooth) ** 2)
    lo = np.array([grid.depths[0] / _MM, model.log_mobility_bounds[0]])
    hi = np.array([grid.depths[-1] / _MM, model.log_mobility_bounds[1]])

    def resid(x):
        return w * (measured(model.log_displacement(x[0] * _MM, x[1], g), fix_noise) - y)

    nodes = [(dd / _MM, math.log(m)) for dd in grid.depths for m in grid.mobilities]
    x0 = np.array(min(nodes, key=lambda x: float(np.sum(resid(x) ** 2))))
    x0 = np.clip(x0, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo))
    scale = np.array([np.diff(grid.depths).mean() / _MM, np.diff(np.log(grid.mobilities)).mean()])
    res = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    h_mm, lnm = (float(v) for v in res.x)
    if _at_edge(h_mm, lo[0], hi[0]):
        raise NotIdentified(f"the side passes' best oil depth is the grid's edge {h_mm:.3g} mm (models/identify.toml "
                            f"[side] depth_grid_mm {lo[0]:g}-{hi[0]:g} mm): the oil is outside it, or the plant does "
                            "not fit these passes")
    if _at_edge(lnm, lo[1], hi[1]):
        raise NotIdentified(f"the side passes' best sphere mobility is the grid's edge {math.exp(lnm):.3g} "
                            f"(models/identify.toml [side] mobility_grid_ratio {math.exp(lo[1]):g}-"
                            f"{math.exp(hi[1]):g}): the spheres move outside it, or the plant does not fit these "
                            "passes")
    r = res.fun
    s2 = float(r @ r) / (n - 2)                   # weighted: the scale of the covariance
    raw = r / w                                   # ln D_s residuals, for the log sd and R² a reader compares
    jtj = res.jac.T @ res.jac
    if np.linalg.cond(jtj) > 1e12:
        raise NotIdentified(f"the side passes at {_span(g)} do not separate oil depth from sphere mobility: "
                            "need passes over a wider range of gaps")
    cov = s2 * np.linalg.inv(jtj)                                   # (H [mm], ln m)
    h_sd_mm, lnm_sd = math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])
    corr = float(cov[0, 1] / (h_sd_mm * lnm_sd)) if h_sd_mm * lnm_sd > 0 else 0.0
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(raw @ raw) / ss_tot if ss_tot > 0 else 1.0

    ids = np.unique(grp)
    per_group: dict[int, float] = {}
    if len(ids) >= 2:
        for gid in ids:
            sel = grp == gid

            def one(x, sel=sel):
                return w[sel] * (measured(model.log_displacement(h_mm * _MM, x[0], g[sel]), fix_noise) - y[sel])

            rg = least_squares(one, [lnm], bounds=(lo[1:], hi[1:]), x_scale=scale[1:], xtol=1e-12, ftol=1e-12)
            if _at_edge(float(rg.x[0]), lo[1], hi[1]):
                raise NotIdentified(f"sphere (group) {int(gid)}'s mobility is the grid's edge {math.exp(rg.x[0]):.3g} "
                                    f"(models/identify.toml [side] mobility_grid_ratio): a stuck or free sphere "
                                    "outside the grid; leave its passes out or widen the grid")
            per_group[int(gid)] = float(rg.x[0])
        between = float(np.std(list(per_group.values()), ddof=1))
        total = max(lnm_sd, between / math.sqrt(len(ids)))
        source = "groups"
    else:
        between = _release_log_sd()
        total = math.hypot(lnm_sd, between / math.sqrt(len(ids)))
        source = "model"
    mean = math.exp(lnm + 0.5 * between**2)
    log_sd = math.sqrt(float(raw @ raw) / (n - 2))
    return PlantFit(h_mm * _MM, h_sd_mm * _MM, mean, mean * total, lnm, lnm_sd, total, between, source,
                    {kk: math.exp(v) for kk, v in per_group.items()}, corr, log_sd, r2, n, k, len(ids),
                    outside, model)


# --- both ------------------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class SideFit:
    """Both fits of the side passes (:func:`fit_side`).

    Attributes
    ----------
    eq22 : Eq22Fit
        ``D_s = a·exp(−b·D_g)`` (eq 22's form) → ``push.toml [side_fit]``.
    plant : PlantFit
        Lid depth and mean sphere mobility → ``fluid.toml [domain] depth_mm``, ``sphere.toml [variability]
        mobility_ratio``.
    evidence : str
        What the passes came from (the caller's text).
    dropped : int
        Passes dropped for ``D_s ≤ 0``, ``D_g ≤ 0`` or non-finite values.
    """

    eq22: Eq22Fit
    plant: PlantFit
    evidence: str
    dropped: int

    def _prefix(self) -> str:
        text = self.evidence.strip()
        if self.dropped:
            text += f" ({self.dropped} passes dropped: D_s <= 0, D_g <= 0 or not finite)"
        return text

    def estimates(self) -> list[Estimate]:
        """``push.toml [side_fit] amplitude_um, rate_per_um``, ``fluid.toml [domain] depth_mm`` and
        ``sphere.toml [variability] mobility_ratio``, each with its standard uncertainty in its key's unit."""
        e, p, pre = self.eq22, self.plant, self._prefix()
        fit22 = f"{pre}: {e.describe()}"
        plant = f"{pre}: {p.describe()}"
        return [
            Estimate("push.toml", "side_fit", "amplitude_um", e.amplitude / _UM, e.amplitude_sd / _UM, fit22),
            Estimate("push.toml", "side_fit", "rate_per_um", e.rate * _UM, e.rate_sd * _UM, fit22),
            Estimate("fluid.toml", "domain", "depth_mm", p.depth / _MM, p.depth_sd / _MM, plant),
            Estimate("sphere.toml", "variability", "mobility_ratio", p.mobility, p.mobility_sd,
                     f"{plant}; {p.mobility_note()}"),
        ]

    def curves(self, gaps=None, points: int = 121) -> dict[str, np.ndarray]:
        """Predicted curves for a report figure: ``{"gap": D_g, "eq22": D_s, "plant": D_s}`` [m] over ``gaps``
        (by default ``points`` gaps across the model grid's gap range); the plant's is NaN outside that range."""
        if gaps is None:
            grid = self.plant.model.grid
            gaps = np.linspace(grid.gaps[0], grid.gaps[-1], points)
        g = np.asarray(gaps, float)
        return {"gap": g, "eq22": self.eq22.predict(g), "plant": self.plant.predict(g)}


def fit_side(gaps_m, displacement_m, group, evidence: str, *, model: SidePushModel | None = None,
             fix_noise: float = 0.0) -> SideFit:
    """Identify the side-push curve from logged side passes (paper §IV-D Fig 6, eq 22-23).

    Parameters
    ----------
    gaps_m : array (n,)
        The achieved gap ``D_g`` of each pass, sphere centre to the robot's path line [m].
    displacement_m : array (n,)
        The sphere's net displacement ``D_s`` over the pass [m].
    group : array (n,) of int
        The sphere / run each pass belongs to (the between-sphere scatter of the mobility).
    evidence : str
        What the passes came from ("42 side passes of run-3.jsonl, frames 120-9810"), opening each estimate's
        evidence.
    model : SidePushModel, optional
        The flow solver's curves (:func:`side_model`: ``models/identify.toml [side]``, built once per process).

    Returns
    -------
    SideFit
        Eq 22's ``a``, ``b`` (:func:`fit_eq22`) and the plant's lid depth and mean mobility (:func:`fit_plant`).
        Passes with ``D_s ≤ 0`` or non-finite values are dropped and counted.

    Raises
    ------
    NotIdentified
        Either fit is not possible (too few passes or gaps; the plant's optimum on its grid's edge); the reason
        names what is missing. :func:`fit_eq22` and :func:`fit_plant` can be called on their own.
    IdentifyError
        Arrays of different lengths or non-integer group ids.
    """
    g, d, grp, dropped = _passes(gaps_m, displacement_m, group)
    eq22 = fit_eq22(g, d)
    plant = fit_plant(g, d, grp, model=model, fix_noise=fix_noise)
    return SideFit(eq22, plant, str(evidence), dropped)
