"""Shared pieces of the push tasks: the mix-in every task is (:class:`PushTask`: ports, common state, parameters,
the kernels' packed parameters), its status codes, the spheres' radii and the kernels' unused-law dummies.

What the tasks share with blocks below them lives below them: the side-push models ``F`` of eq 22/23 in
:mod:`magctl.control.side_models`, the parameter records of ``models/push.toml`` in :mod:`magctl.control.push_params`.
Everything is SI (metres).
"""

from __future__ import annotations

import numpy as np

from magctl.config import load_model
from magctl.control.curve_learning import CurveLearningLaw
from magctl.control.learning import LearningLaw
from magctl.control.phases import START
from magctl.control.push_params import LAW_CURVE, LAW_INTEGRATOR, LAW_RELEASE, PushParams
from magctl.control.release_model import ReleasePolicyLaw
from magctl.control.status import Status
from magctl.core.errors import MagctlError

RUNNING, CONVERGED, ATTEMPT_LIMIT = Status.RUNNING, Status.CONVERGED, Status.ATTEMPT_LIMIT
TRACKING_LOST, SPHERE_LOST, STALLED = Status.TRACKING_LOST, Status.SPHERE_LOST, Status.STALLED


def sphere_radii() -> tuple[float, float]:
    """``(R_1, R_2)`` of eq 21 (m): the sphere radius of ``models/sphere.toml`` for both."""
    r = float(load_model("sphere").sphere.radius)
    return r, r


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
    """The task's parameter record (:mod:`magctl.control.push_params`)."""

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
        """``(p, gain)``: the kernels' :class:`~magctl.control.push_params.TaskParams` — the record's fields by
        name, the spheres, the law's kind and ``derived`` (what the task computes) — and the integrator law's gain
        (a dummy 0 for the other laws)."""
        idx = self.sphere_indices
        law = self._law_kind()
        p = self.params.packed(i0=idx[0], i1=idx[-1], pair=len(idx) > 1, law=law, **derived)
        gain = self.law.gain if law == LAW_INTEGRATOR else 0.0
        return p, np.atleast_1d(np.asarray(gain, dtype=float)).copy()

    def _law_kind(self) -> int:
        """The kernels' code of the task's law (:data:`magctl.control.push_params.LAW_INTEGRATOR` …)."""
        return {LearningLaw: LAW_INTEGRATOR, CurveLearningLaw: LAW_CURVE,
                ReleasePolicyLaw: LAW_RELEASE}[type(self.law)]

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
