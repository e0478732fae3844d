"""Side pushing (§V-B, eq 16–18) as a batched attempt-level state machine at 30 Hz.

One attempt, per trial:

1. measure ``D_s,des = min(|P_g − P_s|, D_max)`` (eq 16, bounded so the gap stays at or
   above ``min_gap``: ``D_max = F⁻¹(min_gap)``), and the gap
   ``D_g = max(F(D_s,des + Δ), min_gap)`` (eq 17, ``F`` = eq 23 or eq 22);
2. ``REPOSITION`` — go round the sphere at ``clearance`` (≥ 650 µm, §VI) to the start of
   the motion line, ``behind`` (1 mm) behind the sphere, ``D_g`` to the side of the line
   sphere → goal (on the side the robot is already on);
3. ``PASS`` — move along the motion line to ``ahead`` past the sphere;
4. ``SETTLE`` — wait, then measure ``D_s,act`` along the line; eq 12 ends the task,
   otherwise the eq 18 law block takes ``e = D_s,act − D_s,des``.

When ``D_s,des + Δ ≤ 0`` (possible after an over-push with ``K_s`` ≥ 1 or a plant stronger than
the model) eq 22 gives an infinite gap: the attempt makes no pass, settles and measures
``D_s,act = 0`` (the no-push branch of :mod:`magctl.stability.switched`).

With ``dirt_response="front-first"`` the task starts with that front push, for the coarse move (the paper's own
advice, §IV-D, §V-C: front pushing is the faster coarse move, side pushing the finer), then passes as below.
With ``dirt_response="front"`` (and the curve law) a sphere the estimate reads as stuck — under
``[dirt] mobility`` of the prior's displacement at the contact threshold with more than ``[dirt] passes``
passes to go — gets one front push to the goal (:class:`~magctl.control.push.front.FrontPushTask`, eq 11's
tolerance ``[dirt] push_tol``) instead of the next pass, at most ``[dirt] fronts`` times. The side stage is frozen
while it runs; its end counts as an attempt (a failure — tracking or sphere lost, stalled — ends the task with
that status), and the side passes then finish from where the sphere lies, with the estimate they had learned.

The naive controllers of §VI-B (a fixed gap, no model) are ``fixed_gap=``. With ``learning="curve"`` the
eq 17–18 pair is replaced by :class:`~magctl.control.curve_learning.CurveLearningLaw`: the curve itself is
re-estimated after every pass from the gap commanded and the displacement measured, ``D_s,des`` is bounded by
the estimate's displacement at ``min_gap`` and the gap inverts the estimate (docs/push-control.md §6).
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.control.curve_learning import CurveLearningLaw, curve_learning_law
from magctl.control.learning import LearningLaw, side_push_law
from magctl.control.phases import FINISHED, DirtStage, SidePhase
from magctl.control.push.common import PushTask, curve_dummies
from magctl.control.push.front import FrontPushTask
from magctl.control.push_params import MODEL_EXP, MODEL_LIN, MODEL_TABLE, CommonParams, DirtParams, SideParams
from magctl.control.side_models import SIDE_MODELS, ExpSideModel, LinSideModel, TabulatedSideModel, side_model
from magctl.core.block import Block
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port

REPOSITION, PASS, SETTLE = int(SidePhase.REPOSITION), int(SidePhase.PASS), int(SidePhase.SETTLE)
SIDE_STAGE, FRONT_STAGE = int(DirtStage.SIDE), int(DirtStage.FRONT)
KERNEL_MODELS = (ExpSideModel, LinSideModel, TabulatedSideModel)
"""The kinds of side-push model the task's kernels evaluate (:func:`magctl.control.push.kernels.model_gap`)."""


class SidePushTask(PushTask, Block):
    """Side pushing of sphere ``sphere`` to ``goal`` with the eq 18 learning law.

    Parameters
    ----------
    goal : (2,) or (B, 2) array_like
        ``P_g`` (m).
    law : LearningLaw or CurveLearningLaw, optional
        The learning block itself (shared with the iteration-domain analysis); overrides ``learning``. A law of
        another type is refused: the task's kernels run these two.
    fixed_gap : float, optional
        Pass at this gap every time (the paper's naive 370/500 µm controllers).
    n_spheres, sphere : int
        Width of the ``spheres_est`` port and which sphere to push.
    params : SideParams, optional
        The task's parameters (:class:`~magctl.control.push_params.SideParams`, ``models/push.toml``
        ``[common]`` and ``[side]``); by default the file's.
    **overrides
        Any field of the record (``None`` keeps the value): ``ks`` (``K_s`` of eq 18); ``model`` (``F`` of
        eq 17: ``"lin"`` eq 23, ``"exp"`` eq 22, ``"lin-fit"``/``"exp-fit"`` refitted, or a model object of
        :data:`KERNEL_MODELS`; with ``learning="curve"`` the prior curve, eq 22's form); ``learning``
        (``"eq18"``, or ``"curve"``: :func:`~magctl.control.curve_learning.curve_learning_law`);
        ``push_out_weight``, ``push_out_min`` (with the curve law: the weight of each new measurement of the
        push-out ratio — the sphere's displacement across the pass, away from the robot, per unit displacement
        along it — and the least displacement along the pass that gives one; the pass is turned towards the
        robot's side by ``atan`` of the estimate); ``dirt_response`` (:data:`DIRT_RESPONSES`, ``[dirt]``);
        ``min_gap`` (the contact threshold of Fig 6); ``eps``, ``max_attempts`` (7.5 µm, 30, §VI-B);
        ``behind``, ``ahead``, ``clearance`` (motion-line start and end, keep-out while repositioning, §VI);
        ``pass_speed`` (0.4 mm/s, §IV-C) and the shared ``arrive_tol``, ``travel_speed``, ``settle_frames``,
        ``max_lost_frames``, ``phase_timeout_frames``, ``workspace``.

    Notes
    -----
    Ports: as :class:`~magctl.control.push.front.FrontPushTask`; ``correction`` is ``Δ``; ``gap`` is
    ``D_g`` of the attempt, 0 for an attempt that makes no pass (``D_s,des + Δ ≤ 0``).
    """

    PHASES = {0: "start", REPOSITION: "reposition", PASS: "pass", SETTLE: "settle", FINISHED: "finished"}

    PARAMS = SideParams

    def __init__(self, name: str = "side_push", *, goal=(0.0, 0.0), law: LearningLaw | CurveLearningLaw | None = None,
                 fixed_gap: float | None = None, n_spheres: int = 1, sphere: int = 0,
                 params: SideParams | None = None, **overrides):
        what = f"side push {name!r}"
        self._check_common(what, params, overrides, goal=goal, n_spheres=n_spheres, sphere=sphere)
        model = self.params.model
        self.model = side_model(model) if isinstance(model, str) else model
        if type(self.model) not in KERNEL_MODELS:
            raise MagctlError(f"{what}: its kernels evaluate no model of type {type(self.model).__name__}; "
                              f"give one of {', '.join(SIDE_MODELS)} or an "
                              + ", ".join(cls.__name__ for cls in KERNEL_MODELS))
        self.law = law if law is not None else self._law(what)
        self._check_law("side push", name, (LearningLaw, CurveLearningLaw))
        self.learns_curve = isinstance(self.law, CurveLearningLaw)
        self.front = self._dirt_front(what, name, n_spheres, sphere)
        self.fixed_gap = None if fixed_gap is None else check_positive("fixed_gap", fixed_gap)
        self.d_max = float(self.model.displacement(self.min_gap))
        ins, outs = self._ports(n_spheres)
        outs.append(Port("gap", (), "m"))
        Block.__init__(self, name, inputs=ins, outputs=outs, dt=FRAME_PERIOD_S, feedthrough=True)

    def _law(self, what: str):
        if self.learning == "eq18":
            return side_push_law(self.ks)
        if not hasattr(self.model, "rate"):
            raise MagctlError(f"{what}: learning='curve' learns eq 22's form; give model='exp-fit' "
                              f"or 'exp' as its prior, not {getattr(self.model, 'name', self.model)!r}")
        return curve_learning_law(self.model)

    def _dirt_front(self, what: str, name: str, n_spheres: int, sphere: int) -> FrontPushTask | None:
        """The front push that answers dirt (``dirt_response="front"``, ``models/push.toml`` ``[dirt]``), else
        None."""
        if self.dirt_response == "none":
            return None
        if not self.learns_curve:
            raise MagctlError(f"{what}: dirt_response={self.dirt_response!r} needs learning='curve' (the curve "
                              "law is what reads a stuck sphere and hands over)")
        self.dirt = DirtParams.resolve(f"{what}: [dirt]")
        shared = {f.name: getattr(self.params, f.name) for f in fields(CommonParams)}
        return FrontPushTask(f"{name}_front", goal=self.goal, kc=0.0, delta0=0.0, max_attempts=1,
                             push_tol=self.dirt.push_tol, n_spheres=n_spheres, sphere=sphere, **shared)

    def kernel(self):
        """The frame: :func:`magctl.control.push.kernels.side_step` with eq 18 (reposition → pass → settle → eq 12,
        eq 16–18), ``curve_side_step`` with the curve-learning law (its EKF step, push-out turn, bound and inverse),
        ``side_dirt_step`` with the front push answering dirt."""
        from magctl.control.push import kernels as k
        from magctl.core.kernel import Kernel

        params = self._side_kernel_params()
        if not self.learns_curve:
            return Kernel(step=k.side_step, params=(*params, *curve_dummies()))
        if self.front is None:
            return Kernel(step=k.curve_side_step, params=params)
        return Kernel(step=k.side_dirt_step, in_place=False,
                      params=(*params, *self.front._front_kernel_with_dummies(), float(self.front.law.initial)))

    def _side_kernel_params(self) -> tuple:
        """``(p, gain, gaps, log displacements, rates, cp)``: the task's
        :class:`~magctl.control.push_params.TaskParams` (the model as a kind code and its coefficients), the
        integrator's gain, the tabulated model's arrays and the curve law's parameters (zeros with eq 18)."""
        from magctl.control import kernels as law_kernels

        m = self.model
        table = (np.zeros(2), np.zeros(2), np.zeros(1))
        if type(m) is ExpSideModel:
            kind, m0, m1 = MODEL_EXP, m.amplitude, m.rate
        elif type(m) is LinSideModel:
            kind, m0, m1 = MODEL_LIN, m.intercept, m.slope_
        else:  # a TabulatedSideModel: the constructor takes no other kind
            kind, m0, m1 = MODEL_TABLE, 0.0, 0.0
            table = tuple(np.ascontiguousarray(a, dtype=float) for a in m._tab())
        radii = getattr(self, "radii", (0.0, 0.0))
        curve = {}
        cp, iterations = law_kernels.no_curve(), 0
        if self.learns_curve:
            cp, iterations = self.law.kernel_params()
            curve = dict(prior_at_min_gap=float(self.law.prior_displacement(self.min_gap)))
            if self.front is not None:
                curve |= dict(dirt_mobility=self.dirt.mobility, dirt_passes=self.dirt.passes,
                              max_fronts=self.dirt.fronts, front_first=self.dirt_response == "front-first")
        p, gain = self._kernel_params(
            d_max=self.d_max, fixed=self.fixed_gap is not None,
            fixed_gap=0.0 if self.fixed_gap is None else self.fixed_gap, model=kind, m0=m0, m1=m1, r0=radii[0],
            r1=radii[1], iterations=iterations, **curve)
        return (p, gain, *table, cp)

    def state_vars(self):
        from magctl.core.block import StateVar, substate

        push_out = () if not self.learns_curve else (
            StateVar("push_out", (), description="estimated push-out across a pass per unit displacement along it"),
            StateVar("push_out_n", (), "int64", description="push-out measurements so far"))
        front = () if self.front is None else (
            StateVar("stage", (), "int64", description="1: side passes, 2: the front push answering dirt"),
            StateVar("fronts", (), "int64", description="front pushes started"),
            substate("front", self.front.state_vars(), "the front push answering dirt"))
        return (*self._common_vars(), *push_out, *front,
                StateVar("goal", (2,), symbol="P_g", description="goal, m"),
                StateVar("u", (2,), symbol="u", description="unit pushing direction of the attempt"),
                StateVar("p0", (2,), symbol="P_s", description="sphere position when the attempt began, m"),
                StateVar("start", (2,), description="start of the motion line, m"),
                StateVar("end", (2,), description="end of the motion line, m"),
                StateVar("d_des", (), symbol="D_s,des", description="desired displacement of the attempt (eq 16), m"),
                StateVar("gap", (), symbol="D_g", description="gap of the attempt (eq 17), m"))

    def initial_state(self, batch, rng=None):
        st = self._common_state(batch)
        st["goal"] = np.broadcast_to(self.goal, (batch, 2)).copy()
        for k in ("u", "p0", "start", "end"):
            st[k] = np.zeros((batch, 2))
        st["d_des"] = np.zeros(batch)
        st["gap"] = np.full(batch, np.nan)
        if self.learns_curve:
            st |= {"push_out": np.zeros(batch), "push_out_n": np.zeros(batch, dtype=np.int64)}
        if self.front is not None:
            st |= {"stage": np.full(batch, SIDE_STAGE, dtype=np.int64), "fronts": np.zeros(batch, dtype=np.int64),
                   "front": self.front.initial_state(batch)}
        return st
