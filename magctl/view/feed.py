"""The live feed: the runtime's :class:`~magctl.rig.monitor.RunMonitor` for the live page.

The runtime hands over each frame's event document; the feed keeps a reference to the latest one, the attempt
rows (:class:`~magctl.view.scene.AttemptErrors`) and a bounded history of plot points, and never waits: no lock is
taken on the runtime's side (reference assignments and bounded-deque appends are atomic in CPython), and the web
server's thread only reads. A page that connects mid-run gets the history once, then the latest frames at the rate
it takes them; frames it is too slow for are skipped, never queued.
"""

from __future__ import annotations

import collections
from typing import Any

from magctl.view.scene import AttemptErrors, Passes, scene_of

HISTORY_POINTS = 1800
"""Plot points kept for a page that connects mid-run: the last minute at 30 frames/s."""


def plot_point(event: dict[str, Any]) -> list:
    """The numbers the time plots show for one frame: t, oscillating field, frequency, static field magnitude, the
    six coil currents, lost, paused."""
    cmd = event.get("cmd") or {}
    b = cmd.get("b_static_T") or [0.0, 0.0]
    return [event["obs"]["t_s"], cmd.get("b_osc_T", 0.0), cmd.get("freq_Hz", 0.0), (b[0] ** 2 + b[1] ** 2) ** 0.5,
            list(event["obs"]["currents_A"]), bool(event["obs"]["lost"]), bool(event.get("paused", False))]


class LiveFeed:
    """Latest frame, attempts and history of one running task (see the module docstring)."""

    def __init__(self, history: int = HISTORY_POINTS):
        self.scene: dict[str, Any] | None = None
        self.fields: dict[str, Any] = {}
        self.latest: tuple[dict, dict] | None = None
        self.version = 0
        self.history: collections.deque = collections.deque(maxlen=history)
        self.attempts = AttemptErrors(None)
        self.passes = Passes({})
        self.stop: dict[str, Any] | None = None
        self.image_source = None
        """A callable giving the rig's newest camera frame and pixel calibration, or None (a ``StationRig``'s
        ``camera_view``); the web server calls it, never the runtime."""

    # --- RunMonitor (the runtime's thread) -------------------------------------------------------------------
    def run_started(self, start: dict[str, Any], descriptor: dict[str, Any]) -> None:
        self.fields = descriptor.get("fields", {})
        shape = self.fields.get("obs.spheres_est_m", {}).get("shape") or [None]
        self.scene = scene_of(start, n_spheres=shape[0])
        self.attempts = AttemptErrors(self.scene["goal_m"])
        self.passes = Passes(self.scene["phases"])
        self.version += 1

    def run_frame(self, event: dict[str, Any], status: dict[str, Any]) -> None:
        self.attempts.update(event)
        self.passes.update(event)
        self.history.append(plot_point(event))
        self.latest = (event, status)
        self.version += 1

    def run_stopped(self, stop: dict[str, Any]) -> None:
        self.stop = stop
        self.version += 1

    # --- the web server's side -------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """The page's first document: the scene, the history so far, the attempts, the stop document if any."""
        return {"scene": self.scene, "history": list(self.history), "attempts": list(self.attempts.rows),
                "passes": list(self.passes.rows), "stop": self.stop, "camera": self.image_source is not None}

    def camera_png(self) -> tuple[bytes, list[float]] | None:
        """The newest camera frame as an 8-bit PNG and the affine map of its pixels onto the glass,
        ``[a, b, c, d, e, f]``: ``x = a·j + b·i + c``, ``y = d·j + e·i + f`` for column ``j``, row ``i`` (m).
        None when the rig gives no frames."""
        import io

        import numpy as np
        from PIL import Image

        got = None if self.image_source is None else self.image_source()
        if got is None:
            return None
        image, calibration = got
        pixels = (np.clip(np.nan_to_num(np.asarray(image, dtype=float)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        buf = io.BytesIO()
        Image.fromarray(pixels, mode="L").save(buf, format="PNG", compress_level=1)
        corners = calibration.to_glass(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
        (c, f), (x1, y1), (x2, y2) = corners
        return buf.getvalue(), [x1 - c, x2 - c, c, y1 - f, y2 - f, f]
