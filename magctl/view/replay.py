"""Finished (or crashed) run logs, served to the replay page: scene, attempts, plot series, frames by range.

A log is read once with :func:`magctl.rig.log.read_log` (its parts, a torn last line and a missing stop document
handled there); anything that is not a run log is that function's one-line :class:`~magctl.rig.log.LogError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from magctl.rig.log import LogError, RunLog, read_log
from magctl.view.feed import plot_point
from magctl.view.scene import AttemptErrors, Passes, scene_of

SERIES_POINTS = 4000
"""At most this many points per plotted series (every k-th frame of a longer run)."""
FRAMES_PER_REQUEST = 2000


class ReplayRun:
    """One run log, read and indexed for the page."""

    def __init__(self, path):
        self.path = Path(path)
        self.log: RunLog = read_log(self.path)
        if not self.log.events:
            raise LogError(f"{self.path}: no events to show" + (" (the run crashed before its first frame)"
                                                                if self.log.crashed else ""))
        try:
            self.scene = scene_of(self.log.start, n_spheres=len(self.log.events[0]["obs"]["spheres_est_m"]))
        except ValueError as err:
            raise LogError(f"{self.path}:1: start document: {err}") from None
        attempts, passes = AttemptErrors(self.scene["goal_m"]), Passes(self.scene["phases"])
        for e in self.log.events:
            attempts.update(e)
            passes.update(e)
        self.attempts, self.passes = attempts.rows, passes.rows
        self.times = [e["obs"]["t_s"] for e in self.log.events]

    def info(self) -> dict[str, Any]:
        ev = self.log.events
        return {"path": str(self.path), "name": self.path.name, "scene": self.scene, "n_events": len(ev),
                "first_seq": ev[0]["seq"], "t0_s": self.times[0], "t1_s": self.times[-1],
                "attempts": self.attempts, "passes": self.passes, "stop": self.log.stop, "note": self.log.crash_note(),
                "controls": [{"seq": e["seq"], **c} for e in ev for c in e.get("control", [])]}

    def series(self) -> dict[str, Any]:
        """Every ``k``-th frame's plot point (``k`` so that at most :data:`SERIES_POINTS` remain; the last frame
        always), with its index into the frames."""
        index = self.series_index()
        return {"index": index, "points": [plot_point(self.log.events[i]) for i in index]}

    def robot_path(self) -> dict[str, Any]:
        """The robot's position at the frames :meth:`series` samples (the replay page's trail)."""
        index = self.series_index()
        return {"index": index, "robot_m": [self.log.events[i]["obs"]["robot_est_m"] for i in index]}

    def series_index(self) -> list[int]:
        n = len(self.log.events)
        stride = max(1, -(-n // SERIES_POINTS))
        index = list(range(0, n, stride))
        if index[-1] != n - 1:
            index.append(n - 1)
        return index

    def frames(self, start: int, count: int) -> list[dict[str, Any]]:
        start = max(0, min(int(start), len(self.log.events)))
        return self.log.events[start: start + max(0, min(int(count), FRAMES_PER_REQUEST))]


def open_runs(paths) -> list[ReplayRun]:
    """Every log of ``paths`` read; the first one that is not a readable run log raises its one-line error."""
    return [ReplayRun(p) for p in paths]
