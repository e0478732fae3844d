"""Small controller blocks the rig's task diagrams need around the servo, drive and push tasks.

* :class:`TrackingGuard` — the rig's rule that a task stops the robot while tracking is lost;
* :class:`Tee` — one exported diagram input feeding several blocks;
* :class:`ArrivalStatus` — status of a go-to;
* :class:`Patrol` — endless waypoint target for long runs (the soak benchmark).

Status codes of ``goto`` and ``patrol`` (push tasks use ``magctl.control.push.common``'s, which agree
on 0–3).
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar
from magctl.core.ports import Port

# task status codes on a task diagram's ``status`` output
RUNNING, DONE, FAILED, LOST = 0, 1, 2, 3
STATUS_NAMES = {RUNNING: "running", DONE: "done", FAILED: "failed", LOST: "lost"}


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("bi,bi->b", v, v))


class Tee(Block):
    """Pass-through ``y = u`` that lets one exported diagram input feed several blocks."""

    def __init__(self, name: str, shape=(), unit: str = "1", dtype: str = "float64", dt: float = FRAME_PERIOD_S):
        super().__init__(name, inputs=[Port("u", tuple(shape), unit, dtype)],
                         outputs=[Port("y", tuple(shape), unit, dtype)], dt=dt, feedthrough=True)

    def output(self, state, u):
        return {"y": u["u"]}


class TrackingGuard(Block):
    """Zero speed while tracking is lost: ``speed_out = 0 if lost else speed``; ``stopped`` flags it."""

    def __init__(self, name: str, dt: float = FRAME_PERIOD_S):
        super().__init__(
            name,
            inputs=[Port("speed", (), "m/s"), Port("lost", (), "1", "bool")],
            outputs=[Port("speed", (), "m/s"), Port("stopped", (), "1", "bool")],
            dt=dt, feedthrough=True,
        )

    def output(self, state, u):
        lost = u["lost"].astype(bool)
        return {"speed": np.where(lost, 0.0, u["speed"]), "stopped": lost}


class ArrivalStatus(Block):
    """Status of a go-to: ``DONE`` once arrived, ``LOST`` while tracking is lost, else ``RUNNING``."""

    def __init__(self, name: str, dt: float = FRAME_PERIOD_S):
        super().__init__(name, inputs=[Port("arrived", (), "1", "bool"), Port("lost", (), "1", "bool")],
                         outputs=[Port("status", (), "1")], dt=dt, feedthrough=True)

    def output(self, state, u):
        lost, arrived = u["lost"].astype(bool), u["arrived"].astype(bool)
        return {"status": np.where(lost, float(LOST), np.where(arrived, float(DONE), float(RUNNING)))}


class Patrol(Block):
    """Cycle through waypoints forever: the target moves on when the robot is within ``tol`` of it.

    Used for long runs (the soak benchmark); its ``status`` is always ``RUNNING``.
    """

    def __init__(self, name: str, waypoints, tol: float, dt: float = FRAME_PERIOD_S):
        self.waypoints = np.asarray(waypoints, dtype=float).reshape(-1, 2)
        self.tol = float(tol)
        super().__init__(name, inputs=[Port("robot_est", (2,), "m")],
                         outputs=[Port("target", (2,), "m"), Port("status", (), "1"), Port("lap", (), "1")],
                         dt=dt, feedthrough=False)

    def state_vars(self):
        return (StateVar("i", (), "int64", description="index of the current waypoint"),
                StateVar("lap", (), symbol="n", description="laps completed"))

    def initial_state(self, batch, rng=None):
        return {"i": np.zeros(batch, dtype=np.int64), "lap": np.zeros(batch)}

    def output(self, state, u):
        return {"target": self.waypoints[state["i"]], "status": np.full(state["i"].shape, float(RUNNING)),
                "lap": state["lap"].copy()}

    def update(self, state, u):
        arrived = _norm(u["robot_est"] - self.waypoints[state["i"]]) < self.tol
        i = np.where(arrived, (state["i"] + 1) % len(self.waypoints), state["i"])
        lap = state["lap"] + (arrived & (i == 0))
        return {"i": i, "lap": lap}


