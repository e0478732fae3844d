"""The two devices of a lab rig — a camera and a coil driver — and the contract every adapter keeps.

A lab server (:mod:`magctl.rig.station`) is built from one :class:`Camera` and one
:class:`CoilDriver`; nothing above this module knows which hardware is behind them. The idea is
ros2_control's mock hardware: a simulated device and a real one keep the same contract, and the
same contract test (:mod:`magctl.rig.devices.contract`) checks both.

**Camera.** :meth:`Camera.grab` returns the next frame — a grayscale image with values in
[0, 1], the device's timestamp and the device's frame number — or ``None`` when no frame came
within the timeout. Frame numbers come from the device (a counter, or the capture timestamp
divided by the nominal period where the device stamps its buffers but does not count them);
a gap in the numbers is a dropped frame (:func:`dropped_between`), never a guess from the host's
clock. A device that is gone raises :class:`DeviceError`.

**Coil driver.** :meth:`CoilDriver.write` sets every channel's output
``i_k(t) = dc_k + ac_k · sin(2π f t)`` (:class:`CoilSetpoint`, A and Hz: the static field and the
stick-slip oscillation of the field command, docs/interfaces.md). A driver with a device-side
deadline (:attr:`CoilDriver.device_deadline`) zeroes its outputs by itself when no valid
setpoint arrives within :attr:`CoilDriver.deadline` s — then coil safety does not depend on the
control computer. :meth:`CoilDriver.zero` sets every output to zero and must be safe to call in
any state after :meth:`CoilDriver.open`; :meth:`CoilDriver.readback` returns what the outputs
are set to where the device reports it (else ``None``). A setpoint outside a channel's rating is
refused with :class:`~magctl.rig.interface.CommandRejected` before anything is sent.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from magctl.rig.interface import CoilMap, Command, CommandRejected, RigError


class DeviceError(RigError):
    """A device failed or cannot be reached; the message starts with the device's name."""

    def __init__(self, device: str, message: str):
        self.device = device
        super().__init__(f"{device}: {message}")


# --- camera ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Attributes
    ----------
    image : ndarray, shape (H, W)
        Grayscale, float, values in [0, 1].
    t : float
        The device's timestamp of the exposure, s (monotonic; its origin is the device's).
    number : int
        The device's frame number; consecutive frames differ by one, a larger step is a drop.
    """

    image: np.ndarray
    t: float
    number: int


def dropped_between(previous: int | None, number: int) -> int:
    """Frames lost between frame numbers ``previous`` and ``number`` (0 for consecutive frames)."""
    if previous is None:
        return 0
    return max(0, int(number) - int(previous) - 1)


def to_gray(image: np.ndarray) -> np.ndarray:
    """A camera image as grayscale float in [0, 1]: 8- and 16-bit integers scaled, colour (BGR) averaged."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img.mean(axis=2) if img.dtype.kind == "f" else img.astype(np.float64).mean(axis=2).astype(img.dtype)
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float64) / 65535.0
    return np.clip(img.astype(np.float64), 0.0, 1.0)


class Camera(ABC):
    """A frame source. Subclasses set :attr:`name` and :attr:`period` and implement the four methods."""

    name: str = "camera"
    period: float = 1.0 / 30.0
    """Nominal frame period, s."""

    @abstractmethod
    def open(self) -> None:
        """Connect to the device; raise :class:`DeviceError` naming it when it is not there."""

    @abstractmethod
    def grab(self, timeout: float) -> Frame | None:
        """The next frame, or None when none arrived within ``timeout`` s."""

    @abstractmethod
    def close(self) -> None:
        """Release the device (idempotent)."""

    @property
    @abstractmethod
    def shape(self) -> tuple[int, int]:
        """(height, width) of the frames in pixels (valid after :meth:`open`)."""

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()


# --- coil driver ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CoilSetpoint:
    """Outputs of a coil driver: ``i_k(t) = dc_k + ac_k · sin(2π·freq·t)``.

    Attributes
    ----------
    dc : ndarray, shape (n,)
        Static current of each channel, A (signed).
    ac : ndarray, shape (n,)
        Amplitude of each channel's sine, A (signed: a negative amplitude is the sine's opposite phase).
    freq : float
        Frequency of the sine, Hz (0: static only).
    """

    dc: np.ndarray
    ac: np.ndarray
    freq: float

    def __post_init__(self):
        dc = np.asarray(self.dc, dtype=float).reshape(-1)
        ac = np.asarray(self.ac, dtype=float).reshape(-1)
        if dc.shape != ac.shape:
            raise CommandRejected(f"setpoint has {dc.size} static currents but {ac.size} amplitudes")
        freq = float(self.freq)
        if freq == 0.0:
            ac = np.zeros_like(ac)  # a sine at 0 Hz is zero: every driver reads such a setpoint back alike
        object.__setattr__(self, "dc", dc)
        object.__setattr__(self, "ac", ac)
        object.__setattr__(self, "freq", freq)

    @staticmethod
    def zero(n: int) -> CoilSetpoint:
        return CoilSetpoint(np.zeros(n), np.zeros(n), 0.0)

    @property
    def n(self) -> int:
        return self.dc.size

    def is_zero(self) -> bool:
        return not (np.any(self.dc) or np.any(self.ac))

    def peak(self) -> np.ndarray:
        """Peak current magnitude of each channel ``|dc| + |ac|``, A."""
        return np.abs(self.dc) + np.abs(self.ac)

    def check(self, current_limit: np.ndarray, freq_max: float, device: str) -> None:
        """Raise :class:`CommandRejected` naming the device and channel when the setpoint is not finite or over a
        rating."""
        if not (np.all(np.isfinite(self.dc)) and np.all(np.isfinite(self.ac)) and math.isfinite(self.freq)):
            raise CommandRejected(f"{device}: setpoint is not finite")
        limit = np.asarray(current_limit, dtype=float)
        if self.n != limit.size:
            raise CommandRejected(f"{device}: setpoint has {self.n} channels, the device has {limit.size}")
        over = self.peak() - limit * (1 + 1e-9)
        if np.any(over > 0):
            k = int(np.argmax(over))
            raise CommandRejected(f"{device}: channel {k} peak {self.peak()[k]:.4g} A exceeds its rating "
                                  f"{limit[k]:.4g} A")
        if not 0.0 <= self.freq <= freq_max:
            raise CommandRejected(f"{device}: frequency {self.freq:.4g} Hz is outside [0, {freq_max:.4g}] Hz")


def setpoint_of(cmd: Command, coils: CoilMap) -> CoilSetpoint:
    """The coil outputs of a field command by the actuator's own allocation ``i = A⁺ b``
    (:class:`~magctl.rig.interface.CoilMap`): ``dc`` from ``[b_x, b_y, 0, G_clamp]``, ``ac`` from ``[0, 0, b_osc, 0]``
    (signed, so that every channel's sine adds to the same vertical oscillation)."""
    dc = coils.static_currents(np.asarray(cmd.b_static, dtype=float)[None, :])[0]
    ac = coils.pinv[:, 2] * float(cmd.b_osc)
    return CoilSetpoint(dc, ac, cmd.freq)


def command_of(setpoint: CoilSetpoint, coils: CoilMap) -> Command:
    """The field command coil outputs produce: ``b = A i`` with ``A = (A⁺)⁺`` (the inverse of :func:`setpoint_of`
    for every command; a setpoint outside the allocation's range is projected onto it)."""
    a = np.linalg.pinv(coils.pinv)
    b_static = (a @ setpoint.dc)[:2]
    b_osc = float((a @ setpoint.ac)[2])
    return Command(b_static, abs(b_osc), setpoint.freq)


@dataclass(frozen=True)
class CoilReadback:
    """What a coil driver reports of itself.

    Attributes
    ----------
    setpoint : CoilSetpoint
        The outputs as set now (zero after a deadline trip).
    tripped : bool
        The device's own deadline zeroed the outputs since the last accepted setpoint.
    counters : dict
        Device counters (frames accepted, rejected, deadline trips, ...), names as the device gives them.
    """

    setpoint: CoilSetpoint
    tripped: bool = False
    counters: dict = field(default_factory=dict)


class CoilDriver(ABC):
    """The coils' amplifiers. Subclasses set the attributes below and implement the methods."""

    name: str = "coils"
    n_channels: int = 6
    current_limit: np.ndarray
    """(n_channels,) the device's own ratings, A (final after :meth:`open`); setpoints above them are refused
    before sending."""
    freq_max: float = 1000.0
    """Highest sine frequency the device generates, Hz."""
    deadline: float | None = None
    """Seconds without a valid setpoint after which the outputs go to zero (None: no deadline)."""
    device_deadline: bool = False
    """True when the device itself enforces :attr:`deadline` (it keeps working if the host stops)."""

    @abstractmethod
    def open(self) -> None:
        """Connect; the outputs are zero afterwards. Raise :class:`DeviceError` naming the device."""

    @abstractmethod
    def write(self, setpoint: CoilSetpoint) -> None:
        """Apply ``setpoint`` (checked first with :meth:`CoilSetpoint.check`); raise :class:`DeviceError` when the
        device does not confirm it."""

    @abstractmethod
    def zero(self) -> None:
        """All outputs to zero (after :meth:`open`, in any state); raise :class:`DeviceError` when unconfirmed."""

    def readback(self) -> CoilReadback | None:
        """The device's own report of its outputs, or None where it has none. A read-back (or any heartbeat) never
        restarts the deadline: only a setpoint does, so a host whose control loop froze cannot keep the coils on."""
        return None

    @abstractmethod
    def close(self) -> None:
        """Outputs to zero (best effort) and release the device (idempotent)."""

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()
