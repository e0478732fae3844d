"""Task phases and stages: the one home of the values of the push tasks' ``phase`` port and state.

A push task's ``phase`` (int64, one per trial) is where its attempt-level state machine is: every task starts at
``START`` and ends at ``FINISHED`` (its status is then no longer ``RUNNING``, :mod:`magctl.control.status`); in
between are the task's own phases (:class:`FrontPhase` for §V-A, :class:`SidePhase` for §V-B and the side-push
assembly). A task that runs another inside it reports the inner task's phase plus an offset. The tasks' kernels
(:mod:`magctl.control.push.kernels`) and their numpy references (``tests/reference``) both take their values from
here.
"""

from __future__ import annotations

from enum import IntEnum


class FrontPhase(IntEnum):
    """Phases of the front push (§V-A, eq 10–13) and of the front-push assembly (Fig 3)."""

    START = 0
    APPROACH = 1
    """Servo to ``P_ri`` behind the sphere, round it at the clearance."""
    PUSH = 2
    """Drive along the line until eq 11 holds (or the robot stands where it would with the sphere at ``P_o``)."""
    RETRACT = 3
    """Move back along the line."""
    SETTLE = 4
    """Wait, then measure: eq 12 ends the task, otherwise eq 13 and the next attempt."""
    FINISHED = 99


class SidePhase(IntEnum):
    """Phases of the side push (§V-B, eq 16–18) and of the side-push assembly (§V-C, eq 21)."""

    START = 0
    REPOSITION = 1
    """Go round the sphere to the start of the motion line."""
    PASS = 2
    """Move along the motion line, past the sphere."""
    SETTLE = 3
    """Wait, then measure ``D_s,act``: eq 12 (eq 21) ends the task, otherwise the law and the next attempt."""
    FINISHED = 99


START = int(FrontPhase.START)
"""Phase of a trial whose first attempt has not begun (every push task)."""
FINISHED = int(FrontPhase.FINISHED)
"""Phase of a trial whose status is no longer ``RUNNING`` (every push task)."""

SIDE_PHASE_OFFSET = 10
"""``phase`` output of the front-then-side assembly in its side stage: the side stage's phase plus this offset."""
FRONT_PHASE_OFFSET = 10
"""``phase`` output of the side push while the front push answering dirt runs: the front push's phase plus this."""


class DirtStage(IntEnum):
    """Stage of a side push that answers dirt with a front push (``dirt_response="front"``)."""

    SIDE = 1
    """Side passes."""
    FRONT = 2
    """The front push answering dirt."""


class AssemblyStage(IntEnum):
    """Stage of the front-then-side assembly (Fig 15)."""

    FRONT = 1
    """The front push of sphere 1 onto sphere 2."""
    SIDE = 2
    """Side-push assembly."""
