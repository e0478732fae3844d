"""Shared pieces of the push tasks: side-push models (eq 22, 23), status codes, geometry.

Everything is SI (metres). The paper writes eq 22 and eq 23 in µm; the
constants below are theirs, converted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from magctl.config import load_model
from magctl.control.phases import START
from magctl.control.push.params import RECORDS, PushParams
from magctl.control.status import Status
from magctl.core.errors import MagctlError
from magctl.core.units import UM

RUNNING, CONVERGED, ATTEMPT_LIMIT = Status.RUNNING, Status.CONVERGED, Status.ATTEMPT_LIMIT
TRACKING_LOST, SPHERE_LOST, STALLED = Status.TRACKING_LOST, Status.SPHERE_LOST, Status.STALLED



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


# --- parameters: models/push.toml, through the records of magctl.control.push.params -------------------
def task_parameters(table: str) -> dict[str, tuple[Any, str]]:
    """The parameters of the record named after ``models/push.toml`` table ``table`` (``"front"``, ``"side"``,
    ``"assembly"``, ``"plan"``, ``"common"``) as keyword → (SI default, SI unit)."""
    return RECORDS[table].spec()


def task_defaults(table: str) -> dict:
    """Keyword defaults (SI) of a push task (see :func:`task_parameters`)."""
    return RECORDS[table].defaults()


def with_defaults(table: str, **given) -> dict:
    """``given`` with every None replaced by its :func:`task_defaults` value."""
    defaults = task_defaults(table)
    return {k: defaults[k] if v is None else v for k, v in given.items()}


def sphere_radii() -> tuple[float, float]:
    """``(R_1, R_2)`` of eq 21 (m): the sphere radius of ``models/sphere.toml`` for both."""
    r = float(load_model("sphere").sphere.radius)
    return r, r


def goal_distance(table: str) -> float:
    """Default goal distance of a task (m): how far beyond the sphere, away from the robot (§VI)."""
    return float(load_model("push")[table].goal_distance)


# --- the attempt-level state machine shared by every push task -----------------------------------
# START and FINISHED (magctl.control.phases) begin and end every push task's phases.


class PushTask:
    """Mix-in with what every push task declares: its ports, its common state, its shared parameters, and the
    kernels' parameter arrays (:mod:`magctl.control.push.kernels`, where a push task's frame is written).

    Subclasses are :class:`~magctl.core.block.Block` s that define ``PHASES``. Every frame, per trial: a trial
    whose tracker reports ``lost`` for more than ``max_lost_frames`` consecutive frames ends with
    ``TRACKING_LOST``; one whose sphere estimate is missing (non-finite) or beyond ``workspace`` from its goal
    ends with ``SPHERE_LOST``; one stuck in a phase for ``phase_timeout_frames`` ends with ``STALLED``; a running,
    tracked trial with its sphere found takes the task's own step. Finished trials hold the robot where it was.
    """

    PARAMS: type[PushParams]
    """The task's parameter record (:mod:`magctl.control.push.params`)."""

    def __getattr__(self, name: str):
        """A parameter of the task's record: ``task.eps`` is ``task.params.eps``."""
        params = self.__dict__.get("params")
        if params is not None and name in params.__dataclass_fields__:
            return getattr(params, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _check_common(self, what: str, params, overrides: dict, *, goal, n_spheres, sphere):
        """Resolve the task's record (``params``, or ``models/push.toml``, with ``overrides``) and check the goal and
        the sphere index; errors name the task (``what``) and the parameter."""
        self.params = (self.PARAMS.resolve(what, **overrides) if params is None
                       else params.replace(what, **overrides))
        if not isinstance(self.params, self.PARAMS):
            raise MagctlError(f"{what}: params must be a {self.PARAMS.__name__}, not {type(params).__name__}")
        if not 0 <= int(sphere) < int(n_spheres):
            raise MagctlError(f"{what}: sphere index {sphere} not in 0..{int(n_spheres) - 1}")
        self.goal = np.asarray(goal, dtype=float)
        if self.goal.shape[-1:] != (2,) or self.goal.ndim > 2 or not np.all(np.isfinite(self.goal)):
            raise MagctlError(f"{what}: goal must be finite, shaped (2,) or (B, 2); got {goal!r}")
        self.sphere_indices = (int(sphere),)

    def _ports(self, n_spheres: int):
        from magctl.core.ports import Port

        ins = [Port("robot_est", (2,), "m"), Port("spheres_est", (n_spheres, 2), "m"),
               Port("lost", (), "1", "bool")]
        outs = [Port("target", (2,), "m"), Port("speed_cap", (), "m/s"), Port("status", (), "1", "int64"),
                Port("attempt", (), "1", "int64"), Port("phase", (), "1", "int64"),
                Port("correction", (), "m")]
        return ins, outs

    def _common_state(self, batch: int) -> dict:
        return {
            "phase": np.full(batch, START, dtype=np.int64),
            "status": np.full(batch, RUNNING, dtype=np.int64),
            "attempt": np.zeros(batch, dtype=np.int64),
            "frames": np.zeros(batch, dtype=np.int64),
            "lost_frames": np.zeros(batch, dtype=np.int64),
            "target": np.full((batch, 2), np.nan),
            "speed": np.zeros(batch),
            "law": self.law.initial_state(batch),
        }

    def _common_vars(self) -> tuple:
        """Declarations of the entries :meth:`_common_state` makes."""
        from magctl.core.block import StateVar, substate

        return (StateVar("phase", (), "int64", description="phase of the attempt (the task's PHASES)"),
                StateVar("status", (), "int64", description="status code (RUNNING until the trial ends)"),
                StateVar("attempt", (), "int64", symbol="i", description="attempts finished"),
                StateVar("frames", (), "int64", description="frames spent in the current phase"),
                StateVar("lost_frames", (), "int64", description="consecutive frames with tracking lost"),
                StateVar("target", (2,), symbol="P_t", description="servo target (NaN: hold the robot), m"),
                StateVar("speed", (), symbol="v_cap", description="speed cap of the current phase, m/s"),
                substate("law", self.law.state_vars(), "the learning law's state"))

    def _kernel_params(self, **derived) -> tuple:
        """``(p, gain)``: the kernels' :class:`~magctl.control.push.kernels.TaskParams` — the record's fields by
        name, the spheres, the law's kind and ``derived`` (what the task computes) — and the integrator law's gain
        (a dummy 0 for the other laws)."""
        from magctl.control.push import kernels as k

        idx = self.sphere_indices
        law = self._law_kind()
        p = self.params.packed(i0=idx[0], i1=idx[-1], pair=len(idx) > 1, law=law, **derived)
        gain = self.law.gain if law == k.LAW_INTEGRATOR else 0.0
        return p, np.atleast_1d(np.asarray(gain, dtype=float)).copy()

    def _law_kind(self) -> int:
        """The kernels' code of the task's law (:data:`magctl.control.push.kernels.LAW_INTEGRATOR` …)."""
        from magctl.control.curve_learning import CurveLearningLaw
        from magctl.control.learning import LearningLaw
        from magctl.control.push import kernels as k
        from magctl.control.release_model import ReleasePolicyLaw

        return {LearningLaw: k.LAW_INTEGRATOR, CurveLearningLaw: k.LAW_CURVE,
                ReleasePolicyLaw: k.LAW_RELEASE}[type(self.law)]

    def _check_law(self, what: str, name: str, accepted: tuple[type, ...]) -> None:
        """Refuse a law whose kind the task's kernels do not run (``accepted``: the law classes they do)."""
        if type(self.law) not in accepted:
            raise MagctlError(f"{what} {name!r}: its kernels run no law of type {type(self.law).__name__}; give a "
                              + " or a ".join(cls.__name__ for cls in accepted))


def release_dummies() -> tuple:
    """The release law's tables and neighbours for a front-push kernel whose law is the integrator (never read)."""
    return (1.0, np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1, dtype=np.int64), np.zeros((1, 1), dtype=bool),
            np.zeros((1, 1), dtype=np.int64))


def curve_dummies() -> tuple:
    """The curve law's ``law.cov``, ``push_out`` and ``push_out_n`` for a side-push kernel whose law is the
    integrator (never read)."""
    return np.zeros((1, 9)), np.zeros((1, 1)), np.zeros((1, 1), dtype=np.int64)
