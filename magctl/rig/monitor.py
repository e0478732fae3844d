"""What a run shows outside its loop, and the requests it takes from outside: the hooks of the live view.

The runtime publishes each frame's event document — the one it logs — to a :class:`RunMonitor` (the live view's
feed, :mod:`magctl.view.feed`), and reads stop and pause requests from :class:`RunControls` once a tick. Both are
built so that nothing outside can slow the 30 Hz loop: publishing is a reference handed over (the monitor copies
nothing and waits on nothing), and the requests are a short list taken under a lock no one holds for longer than
an append.

A stop ends the run before the next tick's read (coils zeroed by the deactivation every exit goes through), with
exit status ``stopped``, the reason and the sender in the stop document; a pause holds the robot as the servo's
hold does — the static field keeps its heading, the oscillating field is off — without stepping the controller, so
its integrals, counters and plans wait too; a resume steps it again from the next frame. Pause and resume are
logged on the event of the tick that took them (``control``), and the held ticks are marked ``paused``
(docs/rig.md "Live view").
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

ACTIONS = ("stop", "pause", "resume")


@dataclass(frozen=True)
class ControlRequest:
    """One request: ``action`` (stop, pause, resume), ``by`` (who sent it: the page's address and id), the
    monotonic time it arrived, and ``seen_seq``: the newest frame the sender had been given (None: unknown)."""

    action: str
    by: str
    t_monotonic: float
    seen_seq: int | None = None


class RunControls:
    """Stop, pause and resume requests for a running :class:`~magctl.rig.runtime.Runtime`, from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queue: list[ControlRequest] = []

    def request(self, action: str, by: str, seen_seq: int | None = None) -> ControlRequest:
        """Queue ``action`` from ``by``; the runtime takes it at its next tick."""
        if action not in ACTIONS:
            raise ValueError(f"unknown run control {action!r}; one of {', '.join(ACTIONS)}")
        req = ControlRequest(action, str(by), time.monotonic(), seen_seq)
        with self._lock:
            self._queue.append(req)
        return req

    def take(self) -> list[ControlRequest]:
        """The requests since the last call, oldest first (empty most ticks: no lock taken then)."""
        if not self._queue:
            return []
        with self._lock:
            out, self._queue = self._queue, []
        return out


class RunMonitor(Protocol):
    """Receives a run's documents as the runtime makes them; every method returns at once."""

    def run_started(self, start: dict[str, Any], descriptor: dict[str, Any]) -> None:
        """The start document (task, options, limits, parameter files) and the descriptor's fields."""

    def run_frame(self, event: dict[str, Any], status: dict[str, Any]) -> None:
        """One tick's event document and the runtime's counters (``state``, ``ticks``, ``overruns``,
        ``slow_steps``, ``paused``)."""

    def run_stopped(self, stop: dict[str, Any]) -> None:
        """The stop document (exit status, reason, counters)."""
