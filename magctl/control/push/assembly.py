"""Two-sphere assembly (§V-C, eq 21) by side pushing, and the front-push variant (Fig 3).

Side-push assembly, per attempt: the *adjusted line* leaves sphere 1 at ``θ_n`` to the
line sphere 1 → sphere 2, turned towards the side the robot is on; the *motion line*
is parallel to it at the gap ``D_g`` (eq 17 with ``D_s,des`` the distance still to
close, bounded); the robot passes along it, side-pushing sphere 1 towards sphere 2 and
diverging from sphere 2. Repeat until eq 21: ``|P_s2 − P_s1| ≤ R_1 + R_2 + ε_as``.

The paper's experiment (Fig 15) chains the two: a front push brings sphere 1 against
sphere 2, the pair separates as the robot retracts, and side passes close the gap
(:class:`FrontThenSideAssemblyTask`).
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.control.phases import FINISHED, SIDE_PHASE_OFFSET, AssemblyStage
from magctl.control.push.common import curve_dummies, sphere_radii
from magctl.control.push.front import FrontAssemblyTask
from magctl.control.push.side import SidePushTask
from magctl.control.push_params import AssemblyParams, CommonParams
from magctl.core.block import Block, StateVar, substate
from magctl.core.checks import check_positive
from magctl.core.errors import MagctlError
from magctl.core.ports import Port


class AssemblyTask(SidePushTask):
    """Side-push assembly of sphere ``moved`` onto sphere ``fixed`` (eq 21).

    Parameters
    ----------
    radii : (float, float)
        ``R_1``, ``R_2`` (m); 105 µm for the 210 µm spheres (§II).
    **kw
        Everything :class:`SidePushTask` takes (``law``, ``fixed_gap``, ``params``) and every field of
        :class:`~magctl.control.push_params.AssemblyParams` — ``[side]`` under ``[assembly]``: ``theta_n`` (the
        adjusted line's angle, rad; the paper's experiment used 30°, §VI-C), ``eps_as`` (``ε_as`` of eq 21, m),
        ``ks`` …; ``goal`` is not used.
    """

    PARAMS = AssemblyParams

    def __init__(self, name: str = "assembly", *, n_spheres: int = 2, moved: int = 0, fixed: int = 1, radii=None,
                 **kw):
        if moved == fixed or not (0 <= moved < n_spheres and 0 <= fixed < n_spheres):
            raise MagctlError(f"assembly {name!r}: sphere indices {moved}, {fixed} must differ and be < {n_spheres}")
        if kw.get("dirt_response") not in (None, "none"):
            raise MagctlError(f"assembly {name!r}: dirt_response={kw['dirt_response']!r} answers a single sphere's "
                              "side push; assembly takes 'none'")
        radii = sphere_radii() if radii is None else radii
        self.radii = (check_positive("radius 1", radii[0]), check_positive("radius 2", radii[1]))
        super().__init__(name, n_spheres=n_spheres, sphere=moved, **kw)
        if not self.theta_n < np.pi / 2:
            raise MagctlError(f"assembly {name!r}: theta_n={self.theta_n!r} rad must be in [0, pi/2)")
        self.sphere_indices = (int(moved), int(fixed))


class FrontThenSideAssemblyTask(Block):
    """The paper's Fig 15 protocol: front-push sphere 1 onto sphere 2, then side-push assembly.

    Stage 1 is :class:`FrontAssemblyTask` with ``front_attempts`` attempts (Fig 15b–d: one
    push, after which the spheres separate on retraction). If eq 21 holds when it ends the
    task has converged; otherwise, from the next frame, stage 2 is :class:`AssemblyTask`
    (Fig 15e–f), which starts from where the spheres then are. A failure of stage 1 other
    than its attempt limit (tracking or sphere lost, stalled) ends the task.

    Parameters
    ----------
    front_attempts : int
        Front pushes before side pushing (1, as in Fig 15).
    theta_n, eps_as, radii, ks, model, law, fixed_gap, max_attempts, …
        Options of :class:`AssemblyTask` (the side-push stage); ``eps_as``, ``radii`` and the
        options every push task shares (``models/push.toml`` ``[common]``: ``arrive_tol``,
        ``settle_frames`` …) go to the front stage too.

    Ports: as :class:`AssemblyTask`; ``attempt`` counts both stages' attempts, ``phase`` is the
    front stage's phase in stage 1 and the side stage's plus :data:`SIDE_PHASE_OFFSET` in stage 2,
    and ``stage`` says which stage runs (1 or 2).
    """

    SIDE_PHASE_OFFSET = SIDE_PHASE_OFFSET

    def __init__(self, name: str = "front_side_assembly", *, n_spheres: int = 2, moved: int = 0, fixed: int = 1,
                 front_attempts: int = 1, radii=None, eps_as: float | None = None, **side_options):
        if int(front_attempts) < 1:
            raise MagctlError(f"assembly {name!r}: front_attempts={front_attempts} must be at least 1")
        shared = dict(n_spheres=n_spheres, moved=moved, fixed=fixed, radii=radii, eps_as=eps_as)
        shared |= {f.name: side_options[f.name] for f in fields(CommonParams) if side_options.get(f.name) is not None}
        self.front = FrontAssemblyTask(f"{name}_front", max_attempts=int(front_attempts), **shared)
        self.side = AssemblyTask(f"{name}_side", **(side_options | shared))
        self.front_attempts = int(front_attempts)
        self.max_attempts = self.front_attempts + self.side.max_attempts
        self.sphere_indices = self.side.sphere_indices
        outs = [*self.side.outputs.values(), Port("stage", (), "1", "int64")]
        Block.__init__(self, name, inputs=list(self.side.inputs.values()), outputs=outs, dt=FRAME_PERIOD_S,
                       feedthrough=True)

    @classmethod
    def phase_names(cls) -> dict[int, str]:
        """Names of the ``phase`` output's values (front stage, then side stage offset)."""
        side = {k + cls.SIDE_PHASE_OFFSET: f"side {v}" for k, v in SidePushTask.PHASES.items() if k != FINISHED}
        return {**{k: f"front {v}" for k, v in FrontAssemblyTask.PHASES.items() if k != FINISHED}, **side,
                FINISHED: "finished"}

    def state_vars(self):
        return (StateVar("stage", (), "int64", description="1: front push, 2: side-push assembly"),
                substate("front", self.front.state_vars(), "the front-push stage"),
                substate("side", self.side.state_vars(), "the side-push stage"))

    def initial_state(self, batch, rng=None):
        return {"stage": np.full(batch, AssemblyStage.FRONT, dtype=np.int64), "front": self.front.initial_state(batch),
                "side": self.side.initial_state(batch)}

    def kernel(self):
        """The frame (:func:`magctl.control.push.kernels.front_then_side_step`, or ``front_then_curve_side_step``
        with the curve-learning law in the side stage): the front stage every frame; the side stage, advanced only
        in stage 2, from the frame after the front stage ends at its attempt limit short of eq 21 (on that frame
        the outputs read ``RUNNING``, phase :data:`SIDE_PHASE_OFFSET`)."""
        from magctl.control.push import kernels as k
        from magctl.core.kernel import Kernel

        front = self.front._front_kernel_with_dummies()
        side = self.side._side_kernel_params()
        if self.side.learns_curve:
            return Kernel(step=k.front_then_curve_side_step, params=(*front, *side))
        return Kernel(step=k.front_then_side_step, params=(*front, *side, *curve_dummies()))


__all__ = ["AssemblyTask", "FrontAssemblyTask", "FrontThenSideAssemblyTask"]
