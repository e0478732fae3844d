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

With ``dirt_response="front"`` (and the curve law) a sphere the estimate reads as stuck — under
``[dirt] mobility`` of the prior's displacement at the contact threshold with more than ``[dirt] passes``
passes to go — gets one front push to the goal (:class:`~magctl.control.push.front.FrontPushTask`, eq 11's
tolerance ``[dirt] push_tol``) instead of the next pass; the side passes then finish from where it lies,
with the estimate they had learned.

The naive controllers of §VI-B (a fixed gap, no model) are ``fixed_gap=``. With ``learning="curve"`` the
eq 17–18 pair is replaced by :class:`~magctl.control.curve_learning.CurveLearningLaw`: the curve itself is
re-estimated after every pass from the gap commanded and the displacement measured, ``D_s,des`` is bounded by
the estimate's displacement at ``min_gap`` and the gap inverts the estimate (docs/push-control.md §6).
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.control.curve_learning import CurveLearningLaw, curve_learning_law
from magctl.control.learning import LearningLaw, side_push_law
from magctl.control.phases import FINISHED, FRONT_PHASE_OFFSET, START, DirtStage, SidePhase
from magctl.control.push.common import (
    PushTask,
    around,
    arrived,
    curve_dummies,
    select_state,
    side_model,
    with_defaults,
)
from magctl.control.push.front import FrontPushTask
from magctl.control.status import Status
from magctl.core.batched import cross, norm, perp, unit
from magctl.core.block import Block
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port

REPOSITION, PASS, SETTLE = int(SidePhase.REPOSITION), int(SidePhase.PASS), int(SidePhase.SETTLE)
LEARNING = {"eq18": "the paper's eq 18 law correcting the fixed model F (gain K_s)",
            "curve": "the curve D_s(D_g) re-estimated after every pass and inverted (magctl.control.curve_learning)"}
DIRT_RESPONSES = {"none": "side passes only, whatever the sphere's mobility",
                  "front": "one front push for the coarse part when the curve law reads the sphere as stuck"}
SIDE_STAGE, FRONT_STAGE = int(DirtStage.SIDE), int(DirtStage.FRONT)


class SidePushTask(PushTask, Block):
    """Side pushing of sphere ``sphere`` to ``goal`` with the eq 18 learning law.

    Parameters
    ----------
    goal : (2,) or (B, 2) array_like
        ``P_g`` (m).
    ks : float
        ``K_s`` of eq 18 (used when ``law`` is not given).
    model : "lin", "exp" or a model object
        ``F`` of eq 17: eq 23 (``lin``) or eq 22 (``exp``); with ``learning="curve"``, the prior curve
        (eq 22's form: ``exp`` or ``exp-fit``).
    learning : {"eq18", "curve"}
        The paper's eq 18 law on ``F`` (``ks``), or the curve learned online
        (:func:`~magctl.control.curve_learning.curve_learning_law`, prior ``model``).
    law : LearningLaw or CurveLearningLaw, optional
        The learning block itself (shared with the iteration-domain analysis); overrides ``learning``.
    push_out_weight, push_out_min : float
        With the curve law: the weight of each new measurement in the estimate of the push-out ratio (the
        sphere's displacement across the pass, away from the robot, per unit displacement along it), and the
        least displacement along the pass that gives a measurement (m). The pass is turned towards the
        robot's side by ``atan`` of the estimate so that the displacement points at the goal.
    dirt_response : {"none", "front"}
        What the curve law does on a sphere it reads as stuck (:data:`DIRT_RESPONSES`; ``models/push.toml``
        ``[dirt]``).
    fixed_gap : float, optional
        Pass at this gap every time (the paper's naive 370/500 µm controllers).
    min_gap : float
        Lower bound of ``D_g`` (370 µm, the contact threshold of Fig 6).
    eps, max_attempts
        ``ε_p`` = 7.5 µm and 30 attempts (§VI-B).
    behind, ahead, clearance : float
        Motion-line start behind the sphere (1 mm, §VI), end past it, and the distance
        kept while repositioning round the sphere (650 µm, §VI) (m).
    pass_speed, travel_speed : float
        ``speed_cap`` along the motion line (0.4 mm/s, §IV-C) and otherwise (m/s).

    Notes
    -----
    Ports: as :class:`~magctl.control.push.front.FrontPushTask`; ``correction`` is ``Δ``; ``gap`` is
    ``D_g`` of the attempt, 0 for an attempt that makes no pass (``D_s,des + Δ ≤ 0``).
    """

    PHASES = {0: "start", REPOSITION: "reposition", PASS: "pass", SETTLE: "settle", FINISHED: "finished"}

    def __init__(self, name: str = "side_push", *, goal=(0.0, 0.0), ks: float | None = None, model=None,
                 learning: str | None = None, law: LearningLaw | CurveLearningLaw | None = None,
                 dirt_response: str | None = None, push_out_weight: float | None = None,
                 push_out_min: float | None = None, fixed_gap: float | None = None, n_spheres: int = 1,
                 sphere: int = 0, min_gap: float | None = None, eps: float | None = None,
                 max_attempts: int | None = None, behind: float | None = None, ahead: float | None = None,
                 clearance: float | None = None, arrive_tol: float | None = None, pass_speed: float | None = None,
                 travel_speed: float | None = None, settle_frames: int | None = None,
                 max_lost_frames: int | None = None, phase_timeout_frames: int | None = None,
                 workspace: float | None = None):
        p = with_defaults("side", ks=ks, model=model, learning=learning, dirt_response=dirt_response,
                          push_out_weight=push_out_weight, push_out_min=push_out_min,
                          min_gap=min_gap, eps=eps,
                          max_attempts=max_attempts, behind=behind, ahead=ahead, clearance=clearance,
                          arrive_tol=arrive_tol,
                          pass_speed=pass_speed, travel_speed=travel_speed, settle_frames=settle_frames,
                          max_lost_frames=max_lost_frames, phase_timeout_frames=phase_timeout_frames,
                          workspace=workspace)
        self._check_common("side push", name, p, goal=goal, n_spheres=n_spheres, sphere=sphere)
        model, min_gap, behind, ahead, pass_speed = p["model"], p["min_gap"], p["behind"], p["ahead"], p["pass_speed"]
        self.model = side_model(model) if isinstance(model, str) else model
        self.law = law if law is not None else self._law(name, p["learning"], p["ks"])
        self.learns_curve = isinstance(self.law, CurveLearningLaw)
        self.push_out_weight = float(p["push_out_weight"])
        if not 0.0 < self.push_out_weight <= 1.0:
            raise MagctlError(f"side push {name!r}: push_out_weight={self.push_out_weight!r} must be in (0, 1]")
        self.push_out_min = check_positive("push_out_min", p["push_out_min"])
        self.front = self._dirt_front(name, p["dirt_response"], n_spheres, sphere, p)
        self.fixed_gap = None if fixed_gap is None else check_positive("fixed_gap", fixed_gap)
        self.min_gap = check_positive("min_gap", min_gap)
        self.d_max = float(self.model.displacement(self.min_gap))
        self.behind = check_positive("behind", behind)
        self.ahead = check_positive("ahead", ahead)
        self.pass_speed = check_positive("pass_speed", pass_speed)
        ins, outs = self._ports(n_spheres)
        outs.append(Port("gap", (), "m"))
        Block.__init__(self, name, inputs=ins, outputs=outs, dt=FRAME_PERIOD_S, feedthrough=True)

    def _law(self, name: str, learning: str, ks: float):
        if learning == "eq18":
            return side_push_law(ks)
        if learning == "curve":
            if not hasattr(self.model, "rate"):
                raise MagctlError(f"side push {name!r}: learning='curve' learns eq 22's form; give model='exp-fit' "
                                  f"or 'exp' as its prior, not {getattr(self.model, 'name', self.model)!r}")
            return curve_learning_law(self.model)
        raise MagctlError(f"side push {name!r}: learning={learning!r} is not one of {', '.join(LEARNING)}")

    def _dirt_front(self, name: str, response: str, n_spheres: int, sphere: int, p: dict) -> FrontPushTask | None:
        """The front push that answers dirt (``dirt_response="front"``), else None."""
        if response not in DIRT_RESPONSES:
            raise MagctlError(f"side push {name!r}: dirt_response={response!r} is not one of "
                              f"{', '.join(DIRT_RESPONSES)}")
        if response == "none":
            return None
        if not self.learns_curve:
            raise MagctlError(f"side push {name!r}: dirt_response='front' needs learning='curve' (the curve law "
                              "is what reads a stuck sphere)")
        dirt = load_model("push").dirt
        self.dirt_mobility = check_positive("[dirt] mobility", float(dirt.mobility))
        self.dirt_passes = float(dirt.passes)
        self.max_fronts = int(dirt.fronts)
        shared = {k: p[k] for k in ("arrive_tol", "travel_speed", "settle_frames", "max_lost_frames",
                                    "phase_timeout_frames", "workspace")}
        return FrontPushTask(f"{name}_front", goal=self.goal, kc=0.0, delta0=0.0, max_attempts=1,
                             push_tol=float(dirt.push_tol), n_spheres=n_spheres, sphere=sphere, **shared)

    def kernel(self):
        """The compiled frame: :func:`magctl.control.push.kernels.side_step` with eq 18, ``curve_side_step`` with the
        curve-learning law (its EKF step, push-out turn, bound and inverse), ``side_dirt_step`` with the front push
        answering dirt; None for a model or law the kernels do not know."""
        from magctl.control.push import kernels as k
        from magctl.core.kernel import Kernel

        law = self._law_kind()
        params = self._side_kernel_params()
        if params is None or law not in (k.LAW_INTEGRATOR, k.LAW_CURVE):
            return None
        if law == k.LAW_INTEGRATOR:
            return Kernel(step=k.side_step, params=(*params, *curve_dummies()))
        if self.front is None:
            return Kernel(step=k.curve_side_step, params=params)
        front_x0 = np.asarray(self.front.law.initial, dtype=float)
        if self.front._law_kind() != k.LAW_INTEGRATOR or front_x0.ndim:
            return None
        return Kernel(step=k.side_dirt_step, in_place=False,
                      params=(*params, *self.front._front_kernel_with_dummies(), float(front_x0)))

    def _side_kernel_params(self) -> tuple | None:
        """``(fp, ip, gain, gaps, log displacements, rates, cp)``: the model as a kind code and its parameters, and
        the curve law's (zeros with eq 18); None for a model of another kind."""
        from magctl.control import kernels as law_kernels
        from magctl.control.push import kernels as k
        from magctl.control.push.common import ExpSideModel, LinSideModel, TabulatedSideModel

        m = self.model
        table = (np.zeros(2), np.zeros(2), np.zeros(1))
        if type(m) is ExpSideModel:
            kind, m0, m1 = k.MODEL_EXP, m.amplitude, m.rate
        elif type(m) is LinSideModel:
            kind, m0, m1 = k.MODEL_LIN, m.intercept, m.slope_
        elif type(m) is TabulatedSideModel:
            kind, m0, m1 = k.MODEL_TABLE, 0.0, 0.0
            table = tuple(np.ascontiguousarray(a, dtype=float) for a in m._tab())
        else:
            return None
        radii = getattr(self, "radii", (0.0, 0.0))
        curve = {}
        cp, iterations = np.zeros(law_kernels.N_CP), 0
        if self.learns_curve:
            cp, iterations = self.law.kernel_params()
            curve = dict(PUSH_OUT_WEIGHT=self.push_out_weight, PUSH_OUT_MIN=self.push_out_min,
                         PRIOR_AT_MIN_GAP=float(self.law.prior_displacement(self.min_gap)))
            if self.front is not None:
                curve |= dict(DIRT_MOBILITY=self.dirt_mobility, DIRT_PASSES=self.dirt_passes)
        fp, ip, gain = self._kernel_params(
            MIN_GAP=self.min_gap, D_MAX=self.d_max, BEHIND=self.behind, AHEAD=self.ahead,
            PASS_SPEED=self.pass_speed, FIXED_GAP=0.0 if self.fixed_gap is None else self.fixed_gap,
            THETA_N=getattr(self, "theta_n", 0.0), M0=m0, M1=m1, R0=radii[0], R1=radii[1],
            EPS_AS=getattr(self, "eps_as", 0.0), **curve)
        ip[[k.MODEL, k.FIXED, k.ITERATIONS, k.MAX_FRONTS]] = (kind, self.fixed_gap is not None, iterations,
                                                              getattr(self, "max_fronts", 0))
        return (fp, ip, gain, *table, cp)

    # --- geometry ---------------------------------------------------------------------------------
    def _geometry(self, new, r, spheres):
        """Moved sphere, distance still to go, pushing direction, side of the motion line, eq 12."""
        s = spheres[:, self.sphere_indices[0]]
        to_goal = new["goal"] - s
        u = unit(to_goal)
        side = np.where(cross(u, r - s) >= 0, 1.0, -1.0)
        dist = norm(to_goal)
        return s, dist, u, side, dist < self.eps

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

    def step(self, state, u):
        return self._frame(state, u) if self.front is None else self._frame_with_front(state, u)

    def output(self, state, u):
        return self.step(state, u)[0]

    def update(self, state, u):
        return self.step(state, u)[1]

    def _frame_with_front(self, state, u):
        """One frame of side passes that hand a stuck sphere to one front push and take it back afterwards.

        The side stage is frozen while the front push runs. It hands over on the frame it measures an attempt
        after which the curve law reads the sphere as stuck (estimated displacement at the contact threshold
        under ``dirt_mobility`` of the prior's) with more than ``dirt_passes`` passes at that bound to go, at
        most ``max_fronts`` times; the front push counts as an attempt when it ends, and the side passes
        start afresh from where the sphere lies. A front push ending in a failure (tracking or sphere lost,
        stalled) ends the task with that status.
        """
        side_state = {k: v for k, v in state.items() if k not in ("stage", "fronts", "front")}
        s_out, s_new = self._frame(side_state, u)
        f_out, f_new = self.front.step(state["front"], u)
        in_front = state["stage"] == FRONT_STAGE
        spheres = np.asarray(u["spheres_est"], dtype=float)
        s = spheres[:, self.sphere_indices[0]]
        dist = norm(s_new["goal"] - s)
        measured = ~in_front & (s_new["attempt"] > side_state["attempt"]) & (s_new["status"] == Status.RUNNING)
        stuck = self.law.mobility(s_new["law"], self.min_gap) < self.dirt_mobility
        many = dist > self.dirt_passes * self.law.displacement(s_new["law"], self.min_gap)
        trigger = measured & stuck & many & (state["fronts"] < self.max_fronts)
        ended = in_front & (f_out["status"] != Status.RUNNING)
        failed = ended & ~np.isin(f_out["status"], (Status.CONVERGED, Status.ATTEMPT_LIMIT))
        back = ended & ~failed

        side = select_state(in_front, side_state, s_new)
        restart = trigger | back
        side["phase"] = np.where(restart, START, side["phase"])
        side["frames"] = np.where(restart, 0, side["frames"])
        side["target"] = np.where(restart[:, None], np.nan, side["target"])
        if back.any():
            self._finish_attempt(side, back, dist < self.eps)  # the front push was an attempt
        side["status"] = np.where(failed, f_out["status"], side["status"])
        side["phase"] = np.where(side["status"] != Status.RUNNING, FINISHED, side["phase"])

        running = select_state(in_front, f_new, state["front"])
        front = select_state(trigger, self.front.initial_state(len(trigger)), running)
        new = side | {"stage": np.where(trigger, FRONT_STAGE, np.where(ended, SIDE_STAGE, state["stage"])),
                      "fronts": state["fronts"] + trigger, "front": front}

        running_front = in_front & ~ended
        out = dict(s_out)
        for k in ("target", "speed_cap"):
            out[k] = np.where(running_front.reshape((-1,) + (1,) * (np.ndim(f_out[k]) - 1)), f_out[k], s_out[k])
        out["phase"] = np.where(running_front, f_out["phase"] + FRONT_PHASE_OFFSET, s_out["phase"])
        out["gap"] = np.where(in_front, 0.0, s_out["gap"])
        out["status"] = side["status"].copy()
        out["attempt"] = side["attempt"].copy()
        out["phase"] = np.where(side["status"] != Status.RUNNING, FINISHED, out["phase"])
        out["target"] = np.where((ended | trigger)[:, None], np.asarray(u["robot_est"], dtype=float), out["target"])
        out["speed_cap"] = np.where(ended | trigger, 0.0, out["speed_cap"])
        return out, new

    def _frame(self, state, u):
        out, new = super()._frame(state, u)
        out["gap"] = np.where(np.isinf(new["gap"]), 0.0, new["gap"])  # 0: the attempt makes no pass
        return out, new

    def _begin(self, new, mask, r, spheres):
        s, dist, u, side, _ = self._geometry(new, r, spheres)
        if self.learns_curve:  # the estimate's own bound and inverse (docs/push-control.md §6)
            # the flow pushes the sphere across the pass, away from the robot: aim so the sum points at the goal
            turn = np.arctan(new["push_out"])
            u = np.cos(turn)[:, None] * u + (side * np.sin(turn))[:, None] * perp(u)
            d_des = np.minimum(dist, self.law.displacement(new["law"], self.min_gap))
        else:
            d_des = np.minimum(dist, self.d_max)  # eq 16, bounded (§V-B step 1)
        if self.fixed_gap is not None:
            gap = np.full(dist.shape, self.fixed_gap)
        elif self.learns_curve:
            gap = self.law.gap(new["law"], d_des, self.min_gap)
        else:
            delta = self.law.output(new["law"], {})["y"]
            gap = np.maximum(self.model.gap(d_des + delta), self.min_gap)  # eq 17
        # D_s,des + Δ ≤ 0: eq 22 asks for an infinite gap, i.e. no pass; the attempt only settles and
        # measures D_s,act = 0 (the no-push branch of magctl.stability.switched)
        skip = mask & ~np.isfinite(gap)
        n = side[:, None] * perp(u) * np.where(np.isfinite(gap), gap, 0.0)[:, None]
        m = mask[:, None]
        new["u"] = np.where(m, u, new["u"])
        new["p0"] = np.where(m, s, new["p0"])
        new["start"] = np.where(m, s - self.behind * u + n, new["start"])
        new["end"] = np.where(m, np.where(skip[:, None], r, s + self.ahead * u + n), new["end"])
        new["d_des"] = np.where(mask, d_des, new["d_des"])
        new["gap"] = np.where(mask, gap, new["gap"])
        self._enter(new, mask & ~skip, REPOSITION)
        self._enter(new, skip, SETTLE)

    def _learn_push_out(self, new, mask, s) -> None:
        """Update the push-out ratio from the attempt just measured: the sphere's displacement across the pass
        line, away from the side the robot passed on, over its displacement along it (passes at least
        ``push_out_min`` long); the first measurement is taken whole, later ones with ``push_out_weight``."""
        u, d = new["u"], s - new["p0"]
        robot_side = np.sign(np.einsum("bi,bi->b", new["start"] - new["p0"] + self.behind * u, perp(u)))
        along = np.einsum("bi,bi->b", d, u)
        across = -robot_side * np.einsum("bi,bi->b", d, perp(u))
        use = mask & (along >= self.push_out_min)
        ratio = across / np.where(use, along, 1.0)
        weight = np.where(new["push_out_n"] == 0, 1.0, self.push_out_weight)
        new["push_out"] = np.where(use, new["push_out"] + weight * (ratio - new["push_out"]), new["push_out"])
        new["push_out_n"] = np.where(use, new["push_out_n"] + 1, new["push_out_n"])

    def _step(self, state, new, r, spheres, ok):
        ph = new["phase"]
        s, *_, done = self._geometry(new, r, spheres)
        self._start(new, ok, done, r, spheres)
        rep = ok & (ph == REPOSITION) & arrived(r, new["start"], self.arrive_tol)
        self._enter(new, rep, PASS)
        passed = ok & (ph == PASS) & arrived(r, new["end"], self.arrive_tol)
        self._enter(new, passed, SETTLE)
        meas = ok & (ph == SETTLE) & (new["frames"] >= self.settle_frames)
        if meas.any():
            d_act = np.einsum("bi,bi->b", s - new["p0"], new["u"])
            go_on = self._finish_attempt(new, meas, done)
            if self.learns_curve:
                new["law"] = self.law.update_where(new["law"], {"gap": new["gap"], "displacement": d_act}, go_on)
                self._learn_push_out(new, go_on, s)
            else:  # eq 18 bracket as printed; the law's gain carries the sign
                new["law"] = self.law.update_where(new["law"], {"e": d_act - new["d_des"]}, go_on)
            self._begin(new, go_on, r, spheres)
        # the servo target and speed cap of the phase, for the trials in ok (the others keep theirs)
        ph = np.where(ok, new["phase"], START)
        tgt = np.where((ph == REPOSITION)[:, None], around(r, s, new["start"], self.clearance), new["target"])
        tgt = np.where(((ph == PASS) | (ph == SETTLE))[:, None], new["end"], tgt)
        new["target"] = tgt
        new["speed"] = np.where(ok, np.where(ph == PASS, self.pass_speed, self.travel_speed), new["speed"])
