"""Numpy reference of the planned assembly's frame (:class:`~magctl.control.push.planned.PlannedAssemblyTask`).

The frame is written here as batched numpy; the plan itself is the library block's Python event
(``handle_event``), which this reference calls at the end of the frame for the trials that raised ``plan_due``,
as both engines do for the kernel.
"""

from __future__ import annotations

import numpy as np

from magctl.control.phases import START
from magctl.control.push.planned import MAX_WAYPOINTS, PASS, REPOSITION, SETTLE, PlannedAssemblyTask
from magctl.control.status import Status
from reference.push_blocks import PushFrame


def rows_of(state: dict, rows: np.ndarray) -> dict:
    """The trials ``rows`` of a (nested) batched state."""
    return {k: rows_of(v, rows) if isinstance(v, dict) else v[rows] for k, v in state.items()}


def put_rows(state: dict, rows: np.ndarray, sub: dict) -> None:
    """Write the trials ``rows`` of ``sub`` back into ``state`` (in place)."""
    for k, v in sub.items():
        if isinstance(v, dict):
            put_rows(state[k], rows, v)
        else:
            state[k][rows] = v


def distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])


class RefPlannedAssembly(PushFrame, PlannedAssemblyTask):
    """Reposition along the waypoints → pass → settle → eq 21 on every bond; a trial that needs a pass raises
    ``plan_due`` and is planned after the frame."""

    @property
    def law_form(self):
        """The planner stays the Python block it is (no numpy twin: it has no kernel)."""
        return self.law

    def step(self, state, u):
        out, new = self._frame(state, u)
        out["gap"] = np.nan_to_num(new["gap"])
        out["correction"] = np.nan_to_num(out["correction"])
        rows = np.flatnonzero(new["plan_due"])
        if rows.size:
            new["law"] = {k: v.copy() for k, v in new["law"].items()}
            put_rows(new, rows, self.handle_event(rows_of(new, rows), {k: np.asarray(v)[rows] for k, v in u.items()}))
        return out, new

    def _spheres_found(self, new, spheres):
        x0, y0, x1, y1 = self.bounds
        pad = self.workspace
        inside = ((spheres[..., 0] > x0 - pad) & (spheres[..., 0] < x1 + pad)
                  & (spheres[..., 1] > y0 - pad) & (spheres[..., 1] < y1 + pad))
        return np.isfinite(spheres).all(axis=(1, 2)) & inside.all(axis=1)

    def _step(self, state, new, r, spheres, ok):
        ph = new["phase"]
        done = self.target.assembled(spheres)
        start = ok & (ph == START)
        new["status"] = np.where(start & done, Status.CONVERGED, new["status"])
        new["plan_due"] = new["plan_due"] | (start & ~done)
        rows = np.arange(len(r))
        idx = np.minimum(new["waypoint"], MAX_WAYPOINTS - 1)
        wp = new["waypoints"][rows, idx]
        last = new["waypoint"] >= new["n_waypoints"] - 1
        tol = np.where(last, self.arrive_tol, self.waypoint_tol)
        at_wp = ok & (ph == REPOSITION) & (distance(r, np.nan_to_num(wp)) < tol)
        new["waypoint"] = np.where(at_wp & ~last, new["waypoint"] + 1, new["waypoint"])
        self._enter(new, at_wp & last, PASS)
        passed = ok & (ph == PASS) & (distance(r, new["end"]) < self.arrive_tol)
        self._enter(new, passed, SETTLE)
        meas = ok & (ph == SETTLE) & (new["frames"] >= self.settle_frames)
        if meas.any():
            new["plan_due"] = new["plan_due"] | self._finish_attempt(new, meas, done)
        ph = np.where(ok, new["phase"], START)
        idx = np.minimum(new["waypoint"], MAX_WAYPOINTS - 1)
        wp = new["waypoints"][rows, idx]
        tgt = np.where((ph == REPOSITION)[:, None], wp, new["target"])
        tgt = np.where(((ph == PASS) | (ph == SETTLE))[:, None], new["end"], tgt)
        new["target"] = tgt
        new["speed"] = np.where(ok, np.where(ph == PASS, self.pass_speed, self.travel_speed), new["speed"])


REFERENCES = {PlannedAssemblyTask: RefPlannedAssembly}
