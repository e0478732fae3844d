"""Deployment on a rig: the rig interface and its implementations, the 30 Hz runtime, run logs.

* :mod:`magctl.rig.interface` — lifecycle, :class:`Command`, :class:`Observation`, limits;
* :mod:`magctl.rig.sim` — :class:`SimRig`, the plant blocks behind the interface, in process;
* :mod:`magctl.rig.server` / :mod:`magctl.rig.client` — the same over ZeroMQ (protocol v2, :mod:`magctl.rig.protocol`);
* :mod:`magctl.rig.runtime` — the fixed-rate loop; :mod:`magctl.rig.tasks` — task registry;
* :mod:`magctl.rig.log` — run logs, export and replay.
"""

from magctl.rig.interface import (
    Command,
    CommandRejected,
    Lifecycle,
    Observation,
    Rig,
    RigConnectionError,
    RigError,
    RigLimits,
    RigStateError,
)

__all__ = ["Command", "CommandRejected", "Lifecycle", "Observation", "Rig", "RigConnectionError", "RigError",
           "RigLimits", "RigStateError"]
