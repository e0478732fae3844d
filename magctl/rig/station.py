"""What a rig server drives: a station — the plant or the lab's devices, stepped frame by frame.

A :class:`Station` holds a limit-checked field command, produces one :class:`~magctl.rig.interface.Observation`
per frame and zeroes the coils on demand. The server (:mod:`magctl.rig.server`) owns the sessions, the protocol,
the watchdog and the clock; the station owns the hardware (or its simulation). Two kinds ship:

* :class:`~magctl.rig.sim.SimPlant` — the plant diagram of the studies (``magctl rig serve-sim``);
* :class:`DeviceStation` — a camera, a frame tracker with its pixel calibration and a coil driver, each an
  adapter of :mod:`magctl.rig.devices` (``magctl rig serve --config lab.toml``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from magctl.rig.devices.base import CoilSetpoint, DeviceError, setpoint_of
from magctl.rig.interface import Command, Lifecycle, Observation, Rig, RigError, RigLimits


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


class DeviceStation:
    """A lab's devices as a station: the camera's frames tracked into observations, commands to the coil driver.

    Each :meth:`step` takes the camera's next frame and tracks it (:class:`~magctl.rig.devices.tracking.FrameTracker`:
    dropped frames from the frame numbers, pixels to glass through the calibration). Each :meth:`apply` checks the
    command against the rig's limits, turns it into channel outputs by the actuator's allocation
    (:func:`~magctl.rig.devices.base.setpoint_of`) and writes them; the board's own deadline zeroes them if the
    writes stop. In real time a grabber thread takes and tracks the frames, so the server never waits for the camera;
    :meth:`step` returns the newest observation (lost when it is older than ``stale_frames`` frames). In lock-step
    (simulated devices only) :meth:`step` grabs and tracks synchronously, one frame per call.

    With ``dry_run`` every command is checked and converted but the coils get zero: the camera, tracker and
    controller can be watched on the rig with the coils off.

    A camera that delivers nothing for ``camera_timeout`` s, or a coil driver that fails, raises
    :class:`~magctl.rig.devices.base.DeviceError` from :meth:`step` / :meth:`apply` / :meth:`zero`; the server then
    zeroes the coils and deactivates with the error as its reason.
    """

    def __init__(self, camera, coils, tracker, limits, *, lockstep: bool = False, period: float = 1 / 30,
                 camera_timeout: float = 1.0, stale_frames: int = 3, dry_run: bool = False, closers=()):
        self.camera, self.coils, self.tracker, self.limits = camera, coils, tracker, limits
        self.lockstep, self.period, self.camera_timeout = lockstep, float(period), float(camera_timeout)
        self.stale_frames, self.dry_run = int(stale_frames), dry_run
        self._misses = 0
        self._closers = list(closers)
        self.n_spheres = tracker.n_spheres
        self.frame = 0
        self.cmd = Command.zero()
        self.last_command_t: float | None = None
        self.setpoint = CoilSetpoint.zero(coils.n_channels)
        self.frames_tracked = 0
        self._closed = False
        self._fault: str | None = None
        camera.open()
        try:
            coils.open()
        except BaseException:
            camera.close()
            raise
        self._last_frame_wall = time.monotonic()
        self.last_frame = None
        self._latest = self.tracker.blank(0.0, 0)
        self.latest = self._latest
        self._lock = threading.Lock()
        self._thread = None
        if not lockstep:
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._grabber, name="magctl-camera", daemon=True)
            self._thread.start()

    # --- frames ---------------------------------------------------------------------------------------
    def _take(self, timeout: float):
        frame = self.camera.grab(timeout)
        if frame is None:
            return None
        self.last_frame = frame
        obs = self.tracker.track(frame)
        self.frames_tracked += 1
        return obs

    def _grabber(self) -> None:
        while not self._stop.is_set():
            try:
                obs = self._take(min(self.camera_timeout, 0.25))
            except DeviceError as err:
                self._fault = str(err)
                return
            except Exception as err:  # noqa: BLE001 - a tracker failure is reported as the camera path's fault
                self._fault = f"{self.camera.name}: tracking failed: {type(err).__name__}: {err}"
                return
            if obs is not None:
                with self._lock:
                    self._latest = obs
                    self._last_frame_wall = time.monotonic()

    def step(self, t: float) -> Observation:
        """This frame's observation stamped ``t`` (the camera's own time and number are in the log's counters)."""
        self.frame += 1
        if self.lockstep:
            obs = self._take(self.camera_timeout)
            if obs is None:
                self._misses += 1
                if self._misses * self.period > self.camera_timeout:
                    raise DeviceError(self.camera.name, f"no frame for {self._misses} frames (camera_timeout "
                                                        f"{self.camera_timeout:g} s); coils zeroed")
                obs = self.tracker.lost_frame()
            else:
                self._misses = 0
            self._latest = obs
            age_frames = 0
        else:
            if self._fault is not None:
                raise DeviceError(self.camera.name, self._fault)
            with self._lock:
                obs, seen = self._latest, self._last_frame_wall
            age = time.monotonic() - seen
            if age > self.camera_timeout:
                raise DeviceError(self.camera.name, f"no frame for {age:.2f} s (camera_timeout "
                                                    f"{self.camera_timeout:g} s); coils zeroed")
            age_frames = age / self.period
        self.latest = Observation(t=t, frame=self.frame, robot_est=obs.robot_est, heading_est=obs.heading_est,
                                  spheres_est=obs.spheres_est, lost=bool(obs.lost or age_frames > self.stale_frames),
                                  currents=self.setpoint.peak())
        return self.latest

    def camera_view(self):
        """The newest camera frame and the pixel calibration that maps it onto the glass (for the live view), or
        None before the first frame. A reference only: the frame is never copied or held for the caller."""
        frame = self.last_frame
        return None if frame is None else (frame.image, self.tracker.calibration)

    # --- coils ----------------------------------------------------------------------------------------
    def apply(self, cmd: Command, now: float) -> np.ndarray:
        currents = self.limits.check(cmd)
        setpoint = setpoint_of(cmd, self.limits.coils)
        # a dry run checks and logs every command but keeps the outputs at zero (the board still gets its frames)
        if self.dry_run:
            setpoint = CoilSetpoint.zero(self.coils.n_channels)
        self.coils.write(setpoint)
        self.cmd, self.setpoint, self.last_command_t = cmd, setpoint, now
        return currents

    def zero(self) -> None:
        self.cmd, self.last_command_t = Command.zero(), None
        self.setpoint = CoilSetpoint.zero(self.coils.n_channels)
        if not self._closed:
            self.coils.zero()

    def status(self) -> dict:
        """Device counters for the server's status reply."""
        rb = self.coils.readback()
        return {"camera": self.camera.name, "coil_driver": self.coils.name, "frames_tracked": self.frames_tracked,
                "frames_dropped": getattr(self.tracker, "dropped", None),
                "coil_board": None if rb is None else {"tripped": rb.tripped, **rb.counters}}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)
        try:
            self.coils.close()
        finally:
            self.camera.close()
            for close in self._closers:
                close()


class StationRig(Rig):
    """Any station behind the rig interface, in-process (``magctl rig run --rig sim`` or ``--rig lab.toml``).

    ``configure`` builds the station; ``read`` advances it by one frame (``realtime=False``: simulated time,
    the rig clock is ``frame · period``) or by every frame due on the monotonic clock. The host-side watchdog
    zeroes the coils when no command came for ``watchdog`` s of rig time (a device-side deadline, where the coil
    driver has one, works on its own besides). A device fault deactivates the rig with the fault as its reason.
    """

    def __init__(self, station: StationFactory, *, limits: RigLimits, watchdog: float, realtime: bool = False,
                 period: float | None = None):
        super().__init__(limits)
        from magctl import FRAME_PERIOD_S

        self.station_factory, self.realtime, self.watchdog = station, realtime, float(watchdog)
        self.period = FRAME_PERIOD_S if period is None else float(period)
        self.plant: Station | None = None
        self.watchdog_trips = 0

    def _now(self) -> float:
        if self.realtime:
            return time.monotonic() - self._t0
        return self.plant.frame * self.period

    def _configure(self) -> None:
        self.plant = self.station_factory()
        self.n_spheres = self.plant.n_spheres
        self._t0 = time.monotonic()

    def _activate(self) -> None:
        self.plant.zero()

    def _advance(self) -> None:
        p = self.plant
        if not self.realtime:
            self._step_frame((p.frame + 1) * self.period)
            return
        now = self._now()
        while (p.frame + 1) * self.period <= now:
            self._step_frame((p.frame + 1) * self.period)

    def _step_frame(self, t: float) -> None:
        p = self.plant
        if p.last_command_t is not None and t - p.last_command_t > self.watchdog:
            age = t - p.last_command_t
            p.zero()
            self.watchdog_trips += 1
            if self.state is Lifecycle.ACTIVE:
                self.state = Lifecycle.INACTIVE
                self.last_error = f"watchdog: no command for {age * 1e3:.0f} ms; coils zeroed"
        p.step(t)

    def _read(self) -> Observation:
        self._advance()
        return self.plant.latest

    def camera_view(self):
        """The station's newest camera frame and its pixel calibration (:meth:`DeviceStation.camera_view`), or
        None: a simulated plant has no camera frames, nor a station before ``configure``."""
        view = getattr(self.plant, "camera_view", None)
        return None if view is None else view()

    def _write(self, cmd: Command) -> None:
        if self.realtime:
            self._advance()
        if self.state is not Lifecycle.ACTIVE:
            raise RigError(self.last_error or "rig is not active")
        self.plant.apply(cmd, self._now())

    def _zero(self) -> None:
        if self.plant is not None:
            self.plant.zero()

    def _close(self) -> None:
        if self.plant is not None:
            self.plant.close()
        self.plant = None
