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
from magctl.control.push.common import PushTask, release_dummies, sphere_radii
from magctl.control.push_params import LAW_RELEASE, FrontParams, goal_distance, with_defaults
from magctl.control.release_model import ReleasePolicyLaw, release_policy_law
from magctl.core.block import Block
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError

APPROACH, PUSH, RETRACT, SETTLE = (int(FrontPhase.APPROACH), int(FrontPhase.PUSH), int(FrontPhase.RETRACT),
                                   int(FrontPhase.SETTLE))


class FrontPushTask(PushTask, Block):
    """Front pushing of sphere ``sphere`` to ``goal`` with the eq 13 learning law.

    Parameters
    ----------
    goal : (2,) or (B, 2) array_like
        ``P_g`` in metres (one for all trials, or one per trial).
    law : LearningLaw or ReleasePolicyLaw, optional
        The learning block to use (shared with the iteration-domain analysis); overrides ``learning``. A law of
        another type is refused: the task's kernels run these two.
    n_spheres, sphere : int
        Width of the ``spheres_est`` port and which sphere to push.
    params : FrontParams, optional
        The task's parameters (:class:`~magctl.control.push_params.FrontParams`, ``models/push.toml``
        ``[common]`` and ``[front]``); by default the file's.
    **overrides
        Any field of :class:`~magctl.control.push_params.FrontParams` (``None`` keeps the value): ``kc`` and
        ``delta0`` (``K_c``, ``δ(0)`` of eq 13), ``learning`` (``"eq13"``, or ``"release"`` — the controller that
        models its own release, :class:`~magctl.control.release_model.ReleasePolicyLaw`, docs/push-control.md
        §7), ``eps`` (``ε_p`` of eq 12), ``push_tol`` (eq 11), ``max_attempts``, ``contact``, ``approach``,
        ``retract``, ``clearance``, ``push_speed`` and the shared ``arrive_tol``, ``travel_speed``,
        ``settle_frames``, ``max_lost_frames``, ``phase_timeout_frames``, ``workspace``.

    Ports
    -----
    inputs ``robot_est`` (2,) m, ``spheres_est`` (N, 2) m, ``lost`` () bool;
    outputs ``target`` (2,) m, ``speed_cap`` () m/s, ``status`` () (codes in
    :mod:`magctl.control.push.common`), ``attempt`` (), ``phase`` (), ``correction`` () m (δ).
    """

    PHASES = {0: "start", APPROACH: "approach", PUSH: "push", RETRACT: "retract", SETTLE: "settle",
              FINISHED: "finished"}

    PARAMS = FrontParams

    def __init__(self, name: str = "front_push", *, goal, law=None, n_spheres: int = 1, sphere: int = 0,
                 params: FrontParams | None = None, **overrides):
        what = f"front push {name!r}"
        self._check_common(what, params, overrides, goal=goal, n_spheres=n_spheres, sphere=sphere)
        self.law = law if law is not None else self._law(what)
        self._check_law("front push", name, (LearningLaw, ReleasePolicyLaw))
        ins, outs = self._ports(n_spheres)
        Block.__init__(self, name, inputs=ins, outputs=outs, dt=FRAME_PERIOD_S, feedthrough=True)

    def _law(self, what: str):
        if self.learning == "eq13":
            return front_push_law(self.kc, self.delta0)
        return release_policy_law(eps=self.eps, goal=goal_distance("front"))

    def kernel(self):
        """The frame (:func:`magctl.control.push.kernels.front_step` with eq 13, ``release_front_step`` with the
        release-model law): approach → push (eq 10, 11) → retract → settle → eq 12, eq 13."""
        from magctl.control.push import kernels as k
        from magctl.core.kernel import Kernel

        if self._law_kind() == LAW_RELEASE:
            return Kernel(step=k.release_front_step,
                          params=(*self._front_kernel_params(), *self.law.policy.kernel_tables()))
        return Kernel(step=k.front_step, params=self._front_kernel_with_dummies())

    def _front_kernel_with_dummies(self) -> tuple:
        """:func:`magctl.control.push.kernels.front_step`'s parameters (eq 13: the release law's are dummies)."""
        return (*self._front_kernel_params(), *release_dummies())

    def _front_kernel_params(self) -> tuple:
        radii = getattr(self, "radii", (0.0, 0.0))
        return self._kernel_params(r0=radii[0], r1=radii[1], eps_as=getattr(self, "eps_as", 0.0))

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
