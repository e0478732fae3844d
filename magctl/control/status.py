"""Task status codes: the one vocabulary of every task's ``status`` port, the rig's run outcomes and the reports.

A task diagram's ``status`` output (int64, one per trial) holds a :class:`Status`.
``RUNNING`` means the task goes on; every other code ends a push task. Whether a
code ends a rig run, and with which exit status, is the task's own ``outcomes``
table (a go-to reports ``TRACKING_LOST`` while tracking is lost and goes on when
it comes back; the runtime's lost timeout ends such a run).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Status(IntEnum):
    """Status of one trial of a task."""

    RUNNING = 0
    """The task goes on."""
    CONVERGED = 1
    """Goal reached: eq 12 (push), eq 21 (assembly), or the servo arrived (go-to)."""
    ATTEMPT_LIMIT = 2
    """The attempt limit was reached without meeting eq 12 / eq 21."""
    TRACKING_LOST = 3
    """Tracking was lost (for longer than the task tolerates, for push tasks)."""
    SPHERE_LOST = 4
    """The pushed sphere's estimate is missing or has left the workspace."""
    STALLED = 5
    """A phase of the task timed out."""

    @property
    def label(self) -> str:
        """Lower-case name used in logs, JSON and reports (``"attempt_limit"``)."""
        return self.name.lower()


STATUS_NAMES: dict[int, str] = {int(s): s.label for s in Status}
"""Code → label, for arrays of codes."""


def status_counts(status: np.ndarray) -> dict[str, int]:
    """Trials per status, by label (every status listed, zero counts included)."""
    status = np.asarray(status)
    return {s.label: int((status == s).sum()) for s in Status}
