"""Small task blocks of the rig's non-push tasks.

* :class:`ArrivalStatus` — status of a go-to;
* :class:`Patrol` — endless waypoint target for long runs (the soak benchmark).

What a task does while tracking is lost is the servo's ``hold`` input (it stops the robot and
freezes its integral) and, for push tasks, their lost-frame limit; both run in the studies too.
Status codes are :class:`magctl.control.status.Status`. Each block's behaviour is its kernel in
:mod:`magctl.control.kernels` (numpy references: ``tests/reference/control_blocks.py``).
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar
from magctl.core.ports import Port


class ArrivalStatus(Block):
    """Status of a go-to: ``CONVERGED`` once arrived, ``TRACKING_LOST`` while tracking is lost, else ``RUNNING``."""

    def __init__(self, name: str, dt: float = FRAME_PERIOD_S):
        super().__init__(name, inputs=[Port("arrived", (), "1", "bool"), Port("lost", (), "1", "bool")],
                         outputs=[Port("status", (), "1", "int64")], dt=dt, feedthrough=True)

    def kernel(self):
        """The compiled status (:func:`magctl.control.kernels.arrival_status_step`)."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(step=k.arrival_status_step)


class Patrol(Block):
    """Cycle through waypoints forever: the target moves on when the robot is within ``tol`` of it.

    Used for long runs (the soak benchmark); its ``status`` is always ``RUNNING``.
    """

    def __init__(self, name: str, waypoints, tol: float, dt: float = FRAME_PERIOD_S):
        self.waypoints = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        self.tol = float(tol)
        super().__init__(name, inputs=[Port("robot_est", (2,), "m")],
                         outputs=[Port("target", (2,), "m"), Port("status", (), "1", "int64"), Port("lap", (), "1")],
                         dt=dt, feedthrough=False)

    def state_vars(self):
        return (StateVar("i", (), "int64", description="index of the current waypoint"),
                StateVar("lap", (), symbol="n", description="laps completed"))

    def initial_state(self, batch, rng=None):
        return {"i": np.zeros(batch, dtype=np.int64), "lap": np.zeros(batch)}

    def kernel(self):
        """The compiled patrol (:func:`magctl.control.kernels.patrol_output`, ``patrol_update``)."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(output=k.patrol_output, update=k.patrol_update,
                      params=(np.ascontiguousarray(self.waypoints), self.tol))
