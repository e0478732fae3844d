"""Front pushing (§V-A, eq 10–13) as a batched attempt-level state machine at 30 Hz.

One attempt, per trial:

1. ``APPROACH`` — servo to ``P_ri``, a point on the pushing line ``P_s → P_g``
   ``approach`` behind the sphere, going round the sphere at ``clearance``;
2. ``PUSH`` — drive along the line until the sphere reaches ``P_o = P_g + δ(i)·u``
   (eq 10), i.e. ``|P_s − P_o| < push_tol`` (eq 11, ``push_tol`` = ε_p = 75 µm as in the paper,
   ``models/push.toml``)
   or the robot is where it would stand with the sphere at ``P_o``;
3. ``RETRACT`` — move ``retract`` back along the line (the fluid pulls the sphere
   ``D_p,r`` after it);
4. ``SETTLE`` — wait ``settle_frames``, then measure: eq 12 ends the task, otherwise
   the eq 13 law block takes ``e = (P_g − P_s)·u`` and the next attempt starts.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.control.learning import LearningLaw, front_push_law
from magctl.control.phases import FINISHED, FrontPhase
from magctl.control.push.common import (
    PushTask,
    goal_distance,
    release_dummies,
    sphere_radii,
    with_defaults,
)
from magctl.control.release_model import ReleasePolicyLaw, release_policy_law
from magctl.core.block import Block
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError

APPROACH, PUSH, RETRACT, SETTLE = (int(FrontPhase.APPROACH), int(FrontPhase.PUSH), int(FrontPhase.RETRACT),
                                   int(FrontPhase.SETTLE))
LEARNING = {"eq13": "the paper's eq 13 law (K_c, δ(0))",
            "release": "the controller that models its own release (magctl.control.release_model)"}


class FrontPushTask(PushTask, Block):
    """Front pushing of sphere ``sphere`` to ``goal`` with the eq 13 learning law.

    Parameters
    ----------
    goal : (2,) or (B, 2) array_like
        ``P_g`` in metres (one for all trials, or one per trial).
    kc, delta0 : float
        ``K_c`` and ``δ(0)`` (m) of the law, used when ``law`` is not given.
    learning : {"eq13", "release"}
        The paper's eq 13 law (``kc``, ``delta0``), or the controller that models its own release
        (:class:`~magctl.control.release_model.ReleasePolicyLaw` on ``models/front_release.toml``,
        docs/push-control.md §7).
    law : LearningLaw or ReleasePolicyLaw, optional
        The learning block to use (shared with the iteration-domain analysis); overrides ``learning``. A law of
        another type is refused: the task's kernels run these two.
    n_spheres, sphere : int
        Width of the ``spheres_est`` port and which sphere to push.
    eps : float
        ``ε_p`` of eq 12 (75 µm, §VI-A).
    push_tol : float, optional
        Tolerance of eq 11 (75 µm, ``models/push.toml``: ε_p, as in the paper).
    max_attempts : int
        Attempt limit (10, §VI-A).
    contact : float
        Robot-centre to sphere-centre distance when touching (m).
    approach, retract, clearance : float
        Distance of ``P_ri`` behind the sphere, retraction length, and the distance kept
        from the sphere while going round it (m).
    arrive_tol : float
        Robot counts as at its target within this distance (m).
    push_speed, travel_speed : float
        ``speed_cap`` while pushing / otherwise (m/s).
    settle_frames, max_lost_frames, phase_timeout_frames : int
        Frames to wait before measuring; frames of tracking loss tolerated; frames
        allowed in one phase before the trial ends as stalled.
    workspace : float
        Sphere farther than this from the goal counts as lost (m).

    Ports
    -----
    inputs ``robot_est`` (2,) m, ``spheres_est`` (N, 2) m, ``lost`` () bool;
    outputs ``target`` (2,) m, ``speed_cap`` () m/s, ``status`` () (codes in
    :mod:`magctl.control.push.common`), ``attempt`` (), ``phase`` (), ``correction`` () m (δ).
    """

    PHASES = {0: "start", APPROACH: "approach", PUSH: "push", RETRACT: "retract", SETTLE: "settle",
              FINISHED: "finished"}

    def __init__(self, name: str = "front_push", *, goal, kc: float | None = None, delta0: float | None = None,
                 learning: str | None = None, law=None, n_spheres: int = 1, sphere: int = 0, eps: float | None = None,
                 push_tol: float | None = None, max_attempts: int | None = None, contact: float | None = None,
                 approach: float | None = None, retract: float | None = None, clearance: float | None = None,
                 arrive_tol: float | None = None, push_speed: float | None = None, travel_speed: float | None = None,
                 settle_frames: int | None = None, max_lost_frames: int | None = None,
                 phase_timeout_frames: int | None = None, workspace: float | None = None):
        p = with_defaults("front", kc=kc, delta0=delta0, learning=learning, eps=eps, push_tol=push_tol,
                          max_attempts=max_attempts, contact=contact,
                          approach=approach, retract=retract, clearance=clearance, arrive_tol=arrive_tol,
                          push_speed=push_speed, travel_speed=travel_speed, settle_frames=settle_frames,
                          max_lost_frames=max_lost_frames, phase_timeout_frames=phase_timeout_frames,
                          workspace=workspace)
        self._check_common("front push", name, p, goal=goal, n_spheres=n_spheres, sphere=sphere)
        self.law = law if law is not None else self._law(name, p)
        self._check_law("front push", name, (LearningLaw, ReleasePolicyLaw))
        self.push_tol = check_positive("push_tol", p["push_tol"])
        self.contact = check_positive("contact", p["contact"])
        self.approach = check_positive("approach", p["approach"])
        self.retract = check_positive("retract", p["retract"])
        self.push_speed = check_positive("push_speed", p["push_speed"])
        ins, outs = self._ports(n_spheres)
        Block.__init__(self, name, inputs=ins, outputs=outs, dt=FRAME_PERIOD_S, feedthrough=True)

    def _law(self, name: str, p: dict):
        if p["learning"] == "eq13":
            return front_push_law(p["kc"], p["delta0"])
        if p["learning"] == "release":
            return release_policy_law(eps=self.eps, goal=goal_distance("front"))
        raise MagctlError(f"front push {name!r}: learning={p['learning']!r} is not one of {', '.join(LEARNING)}")

    def kernel(self):
        """The frame (:func:`magctl.control.push.kernels.front_step` with eq 13, ``release_front_step`` with the
        release-model law): approach → push (eq 10, 11) → retract → settle → eq 12, eq 13."""
        from magctl.control.push import kernels as k
        from magctl.core.kernel import Kernel

        if self._law_kind() == k.LAW_RELEASE:
            return Kernel(step=k.release_front_step,
                          params=(*self._front_kernel_params(), *self.law.policy.kernel_tables()))
        return Kernel(step=k.front_step, params=self._front_kernel_with_dummies())

    def _front_kernel_with_dummies(self) -> tuple:
        """:func:`magctl.control.push.kernels.front_step`'s parameters (eq 13: the release law's are dummies)."""
        return (*self._front_kernel_params(), *release_dummies())

    def _front_kernel_params(self) -> tuple:
        radii = getattr(self, "radii", (0.0, 0.0))
        return self._kernel_params(PUSH_TOL=self.push_tol, CONTACT=self.contact, APPROACH=self.approach,
                                   RETRACT=self.retract, PUSH_SPEED=self.push_speed, R0=radii[0], R1=radii[1],
                                   EPS_AS=getattr(self, "eps_as", 0.0))

    def state_vars(self):
        from magctl.core.block import StateVar

        return (*self._common_vars(),
                StateVar("goal", (2,), symbol="P_g", description="goal, m"),
                StateVar("u", (2,), symbol="u", description="unit pushing direction of the attempt"),
                StateVar("p_ri", (2,), symbol="P_ri", description="approach point behind the sphere, m"),
                StateVar("p_o", (2,), symbol="P_o", description="point the sphere is pushed to, P_g + δu (eq 10), m"),
                StateVar("g_line", (2,), symbol="P_g", description="goal point of the attempt's line, m"),
                StateVar("stand", (2,), description="where the robot stands with the sphere at P_o, m"),
                StateVar("back", (2,), description="end of the retraction, m"))

    def initial_state(self, batch, rng=None):
        st = self._common_state(batch)
        st["goal"] = np.broadcast_to(self.goal, (batch, 2)).copy()
        for k in ("u", "p_ri", "p_o", "g_line", "stand", "back"):
            st[k] = np.zeros((batch, 2))
        return st


class FrontAssemblyTask(FrontPushTask):
    """Assembly by front pushing (§V-C, Fig 3): push sphere 1 to the contact point of sphere 2.

    The goal of each attempt is ``P_s2 − (R_1 + R_2)·v`` with ``v`` the unit vector from
    sphere 1 to sphere 2; the task ends by eq 21, ``|P_s2 − P_s1| ≤ R_1 + R_2 + ε_as``.
    The paper shows this failing: retraction pulls sphere 1 back by ``D_p,r``.
    """

    def __init__(self, name: str = "front_assembly", *, n_spheres: int = 2, moved: int = 0, fixed: int = 1,
                 radii=None, eps_as: float | None = None, **kw):
        if moved == fixed or not (0 <= moved < n_spheres and 0 <= fixed < n_spheres):
            raise MagctlError(f"assembly {name!r}: sphere indices {moved}, {fixed} must differ and be < {n_spheres}")
        radii = sphere_radii() if radii is None else radii
        self.radii = (check_positive("radius 1", radii[0]), check_positive("radius 2", radii[1]))
        eps_as = with_defaults("assembly", eps_as=eps_as)["eps_as"]
        self.eps_as = check_positive("eps_as", eps_as, allow_zero=True)
        if kw.get("learning") not in (None, "eq13"):
            raise MagctlError(f"assembly {name!r}: learning={kw['learning']!r} models a single sphere's release "
                              "towards a goal; front-push assembly takes 'eq13'")
        kw.setdefault("goal", (0.0, 0.0))
        super().__init__(name, n_spheres=n_spheres, sphere=moved, **kw)
        self.sphere_indices = (int(moved), int(fixed))
