"""The simulated rig: plant blocks behind the rig interface.

:class:`SimPlant` is the part shared by the in-process :class:`SimRig` and the
``magctl rig serve-sim`` server: a plant diagram stepped one frame at a time
(B = 1) with a held field command, the server-side current limits and the
watchdog. :class:`SimRig` puts it behind :class:`~magctl.rig.interface.Rig`,
stepping either one frame per ``read()`` (as fast as possible) or in real time
on the monotonic clock.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model
from magctl.core.diagram import Diagram
from magctl.rig.interface import Command, Observation, RigLimits
from magctl.rig.plant import build_sim_plant, check_plant
from magctl.rig.station import StationRig

PlantFactory = Callable[[], Diagram]


class SimPlant:
    """A plant diagram stepped frame by frame with a held, limit-checked command (a station: the watchdog is the
    server's or the :class:`~magctl.rig.station.StationRig`'s).

    Parameters
    ----------
    factory : callable
        Returns the plant diagram (see :func:`magctl.rig.plant.build_sim_plant`).
    limits : RigLimits
        Commands outside them are rejected by :meth:`apply`.
    seed : int
        Seed of the plant's random streams.
    """

    def __init__(self, factory: PlantFactory, limits: RigLimits, seed: int = 0, period: float = FRAME_PERIOD_S):
        self.factory, self.limits, self.seed, self.period = factory, limits, seed, period
        self.diagram = factory()
        check_plant(self.diagram)
        self.n_spheres = self.diagram.outputs["spheres_est"].shape[0]
        self.reset()

    def reset(self) -> None:
        """Plant back to its initial state, coils off, frame 0."""
        self.state = self.diagram.initial_state(1, seed=self.seed)
        self.cmd = Command.zero()
        self.frame = 0
        self.last_command_t: float | None = None
        self._u = self._inputs(self.cmd)
        outs = self.diagram.output(self.state, self._u)
        self.latest = self._observation(0.0, outs)

    def _inputs(self, cmd: Command) -> dict[str, np.ndarray]:
        return {"b_static": cmd.b_static[None, :].copy(), "b_osc": np.array([cmd.b_osc]),
                "freq": np.array([cmd.freq])}

    def _observation(self, t: float, outs) -> Observation:
        return Observation(
            t=t, frame=self.frame,
            robot_est=np.array(outs["robot_est"][0], dtype=float),
            heading_est=float(outs["heading_est"][0]),
            spheres_est=np.array(outs["spheres_est"][0], dtype=float).reshape(-1, 2),
            lost=bool(outs["lost"][0]),
            currents=np.array(outs["currents"][0], dtype=float),
        )

    def apply(self, cmd: Command, now: float) -> np.ndarray:
        """Hold ``cmd`` from now on (after the limit check) and feed the watchdog; returns the currents."""
        currents = self.limits.check(cmd)
        self.cmd = cmd
        self._u = self._inputs(cmd)
        self.last_command_t = now
        return currents

    def zero(self) -> None:
        """Coils off; no command is held (a watchdog has nothing to time until the next)."""
        self.cmd = Command.zero()
        self._u = self._inputs(self.cmd)
        self.last_command_t = None

    def close(self) -> None:
        """Coils off (a simulated plant holds no device)."""
        self.zero()

    def step(self, t: float) -> Observation:
        """Advance one frame under the held command; the observation is stamped ``t``."""
        outs, self.state = self.diagram.step(self.state, self._u)
        self.frame += 1
        # after the update, so the observation is the one the tracker reports at the new frame
        outs = self.diagram.output(self.state, self._u)
        self.latest = self._observation(t, outs)
        return self.latest


class SimRig(StationRig):
    """In-process simulated rig: the studies' plant (:class:`SimPlant`) behind the rig interface.

    Parameters
    ----------
    factory : callable, optional
        Plant factory; ``build_sim_plant(n_spheres)`` by default.
    n_spheres : int
        Spheres in the default scene.
    plant : {"physics", "standin"}
        Plant of the default factory: the physical plant blocks or the fast kinematic stand-in.
    realtime : bool
        False: every ``read()`` advances the plant by exactly one frame and the
        rig clock is ``frame · period`` (as fast as possible, deterministic).
        True: ``read()`` advances the plant by every frame due on the monotonic clock.
    seed : int
        Plant seed.
    """

    def __init__(self, factory: PlantFactory | None = None, *, n_spheres: int = 1, realtime: bool = False,
                 seed: int = 0, limits: RigLimits | None = None, params=None, plant: str = "physics"):
        params = params or load_model("rig")
        limits = limits or RigLimits.from_params(params)
        factory = factory or (lambda: build_sim_plant(n_spheres, params=params, plant=plant))
        self.factory, self.seed = factory, seed
        super().__init__(lambda: SimPlant(factory, limits, seed), limits=limits,
                         realtime=realtime, watchdog=params.watchdog.timeout)
