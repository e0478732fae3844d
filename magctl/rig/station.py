"""What a rig server drives: a station — the plant or the lab's devices, stepped frame by frame.

A :class:`Station` holds a limit-checked field command, produces one :class:`~magctl.rig.interface.Observation`
per frame and zeroes the coils on demand. The server (:mod:`magctl.rig.server`) owns the sessions, the protocol,
the watchdog and the clock; the station owns the hardware (or its simulation). Two kinds ship:

* :class:`~magctl.rig.sim.SimPlant` — the plant diagram of the studies (``magctl rig serve-sim``);
* :class:`DeviceStation` — a camera, a frame tracker with its pixel calibration and a coil driver, each an
  adapter of :mod:`magctl.rig.devices` (``magctl rig serve --config lab.toml``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from magctl.rig.interface import Command, Observation


class Station(Protocol):
    """The methods a rig server calls (under its lock; each must return within a few milliseconds except
    :meth:`step`, which may take one frame)."""

    n_spheres: int
    frame: int
    latest: Observation
    cmd: Command
    last_command_t: float | None

    def apply(self, cmd: Command, now: float) -> np.ndarray:
        """Hold ``cmd`` (limit-checked: :class:`~magctl.rig.interface.CommandRejected` otherwise); the currents."""

    def zero(self) -> None:
        """Coils off now."""

    def step(self, t: float) -> Observation:
        """The next frame's observation, stamped ``t``."""

    def close(self) -> None:
        """Coils off and devices released (idempotent)."""


StationFactory = Callable[[], Station]
