"""The rig interface: lifecycle, observations, field commands and safety limits.

A rig follows the lifecycle of ros2_control's hardware interface::

    unconfigured --configure--> inactive --activate--> active
                                   ^                      |
                                   +------deactivate------+

    any error --> coils zeroed --> inactive (last_error set)
    error while zeroing (rig unreachable) --> error (terminal)

``read()`` returns the latest observation in every state but unconfigured;
``write()`` is accepted only when active. Reactivation is always explicit, and
every activation increments :attr:`Rig.activation` so that the runtime resets
the controller's state.

The command is the drive's field command of docs/interfaces.md — ``b_static``
(2,) T, ``b_osc`` () T, ``freq`` () 1/s — and the observation is the tracker's
output — ``robot_est`` (2,) m, ``heading_est`` rad, ``spheres_est`` (N, 2) m,
``lost`` — with the rig's timestamp and frame number.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from magctl.config import Params, load_model
from magctl.core.errors import MagctlError
from magctl.plant._coilfield import CoilAllocation, load_coils


class RigError(MagctlError):
    """A rig failed or refused an operation."""


class RigStateError(RigError):
    """An operation is not allowed in the rig's current lifecycle state."""


class CommandRejected(RigError):
    """A command is malformed, not finite or outside the limits; it was not applied."""


class RigConnectionError(RigError):
    """The rig (server) cannot be reached; the coils' state is unknown to the client."""


class Lifecycle(enum.StrEnum):
    """Lifecycle states of a rig."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    ERROR = "error"


@dataclass(frozen=True)
class Command:
    """A field command for the coils (SI).

    Attributes
    ----------
    b_static : ndarray, shape (2,)
        In-plane static field in T; its direction sets the robot's heading.
    b_osc : float
        Amplitude of the oscillating field in T (drives stick-slip steps).
    freq : float
        Oscillation frequency in 1/s.
    """

    b_static: np.ndarray
    b_osc: float
    freq: float

    @staticmethod
    def zero() -> Command:
        """Coils off."""
        return Command(np.zeros(2), 0.0, 0.0)

    @staticmethod
    def from_values(b_static, b_osc, freq) -> Command:
        """Build a command, checking shapes and finiteness (raises :class:`CommandRejected`)."""
        try:
            bs = np.asarray(b_static, dtype=float).reshape(-1)
            bo, fr = float(np.asarray(b_osc, dtype=float)), float(np.asarray(freq, dtype=float))
        except (TypeError, ValueError):
            raise CommandRejected(
                f"command fields must be numbers: b_static={b_static!r}, b_osc={b_osc!r}, freq={freq!r}"
            ) from None
        if bs.shape != (2,):
            raise CommandRejected(f"b_static must have 2 elements, got {bs.size}")
        for name, v in (("b_static", bs), ("b_osc", bo), ("freq", fr)):
            if not np.all(np.isfinite(v)):
                raise CommandRejected(f"{name} is not finite: {v!r}")
        return Command(bs, bo, fr)

    def is_zero(self) -> bool:
        return not (np.any(self.b_static) or self.b_osc or self.freq)


@dataclass(frozen=True)
class Observation:
    """One tracker observation (SI).

    Attributes
    ----------
    t : float
        Rig timestamp of the frame in s (the rig's own monotonic clock).
    frame : int
        Frame number since the rig was configured.
    robot_est : ndarray, shape (2,)
        Estimated robot position in m.
    heading_est : float
        Estimated heading in rad.
    spheres_est : ndarray, shape (N, 2)
        Estimated sphere positions in m.
    lost : bool
        Tracking lost: the positions are not to be trusted.
    currents : ndarray, shape (6,)
        Coil currents (peak) in A applied during the frame.
    """

    t: float
    frame: int
    robot_est: np.ndarray
    heading_est: float
    spheres_est: np.ndarray
    lost: bool
    currents: np.ndarray = field(default_factory=lambda: np.zeros(6))

    def write_inputs(self, targets: dict[str, np.ndarray]) -> None:
        """The observation written into B = 1 input arrays in place (those of ``targets`` only, by name)."""
        for name, target in targets.items():
            if name == "robot_est":
                target[0] = self.robot_est
            elif name == "heading_est":
                target[0] = self.heading_est
            elif name == "spheres_est":
                target[0] = self.spheres_est
            elif name == "lost":
                target[0] = self.lost
            else:
                raise KeyError(name)

    def controller_inputs(self) -> dict[str, np.ndarray]:
        """The observation as B = 1 signals named as in docs/interfaces.md."""
        return {
            "robot_est": self.robot_est[None, :],
            "heading_est": np.array([self.heading_est]),
            "spheres_est": self.spheres_est[None, :, :],
            "lost": np.array([self.lost]),
        }


class CoilMap:
    """Field command → coil currents by the six-coil actuator's own allocation (``magctl.plant.coils``).

    The static field ``[b_x, b_y, 0, G_clamp]`` and the oscillation ``[0, 0, b_osc, 0]`` get the
    minimum-norm currents ``i = A⁺ b`` of the actuation matrix ``A`` (4 × 6, from the coil geometry
    in ``models/coils.toml``), exactly as :class:`~magctl.plant.coils.CoilActuator` allocates them.
    A coil's amplifier must deliver the peak ``|i_s| + |i_o|``, which must stay within that coil's
    ``current_limit`` (the same rule at which the actuator starts to saturate).

    Parameters
    ----------
    pinv : (6, 4) array
        ``A⁺``, A per (T, T, T, T/m).
    current_limit : (6,) array
        Continuous current rating of each coil, A.
    clamp_gradient : float
        ``G_clamp`` of the static command, T/m.
    names : sequence of str, optional
        Coil names (``models/coils.toml`` order).
    """

    def __init__(self, pinv, current_limit, clamp_gradient: float = 0.0, names=None):
        self.current_limit = np.asarray(current_limit, dtype=float).reshape(-1)
        pinv = np.asarray(pinv, dtype=float)
        if pinv.shape != (self.current_limit.size, 4) or np.any(self.current_limit <= 0):
            raise RigError(f"coil map needs a (n, 4) allocation and n positive current limits, got "
                           f"{pinv.shape} and {self.current_limit.tolist()}")
        self.allocation = CoilAllocation(pinv, clamp_gradient)
        self.pinv, self.clamp_gradient = self.allocation.pinv, self.allocation.clamp_gradient
        self.names = list(names) if names is not None else [f"coil{i}" for i in range(self.current_limit.size)]
        self._i_clamp = self.allocation.clamp_currents
        self._per_tesla_xy = self.pinv[:, :2]
        self._per_tesla_osc = self.allocation.per_tesla_osc
        # the headroom checks run every 30 Hz tick on the rig: their constant parts are computed once
        self._static_room = self.current_limit - np.abs(self._i_clamp)
        self._osc_carry = self._per_tesla_osc > 1e-9 * self._per_tesla_osc.max()

    @classmethod
    def from_coils(cls, coils=None) -> CoilMap:
        """The map of a :class:`~magctl.plant.coils.CoilSet` (``load_coils()`` when omitted)."""
        coils = load_coils() if coils is None else coils
        alloc = coils.allocation()
        return cls(alloc.pinv, coils.current_limit, alloc.clamp_gradient, [c.name for c in coils.coils])

    @property
    def current_max(self) -> float:
        """The smallest coil rating, A (for summaries; the check is per coil)."""
        return float(self.current_limit.min())

    def static_currents(self, b_static: np.ndarray) -> np.ndarray:
        """Signed static currents ``(B, n)`` A for ``b_static`` ``(B, 2)`` T (the actuator's own allocation)."""
        return self.allocation.static_currents(b_static)

    def osc_currents(self, b_osc: np.ndarray) -> np.ndarray:
        """Current amplitudes ``(B, n)`` A of the oscillation ``b_osc`` ``(B,)`` T."""
        return self.allocation.osc_currents(b_osc)

    def currents(self, b_static: np.ndarray, b_osc: np.ndarray) -> np.ndarray:
        """Peak current magnitudes ``|i_s| + |i_o|`` ``(B, n)`` A each amplifier must deliver."""
        return np.abs(self.static_currents(b_static)) + self.osc_currents(b_osc)

    def static_headroom(self, b_static: np.ndarray) -> float:
        """Largest ``s`` with ``s·b_static`` within every coil's rating (ignoring the clamp term)."""
        need = np.abs(self._per_tesla_xy @ b_static)
        loaded = need > 0
        if not loaded.any():
            return math.inf
        # a floor on the load keeps a vanishing field from overflowing the ratio (it then reads ~1e300, as good as inf)
        return float((self._static_room[loaded] / np.maximum(need[loaded], 1e-300)).min())

    def osc_headroom(self, b_static: np.ndarray) -> float:
        """Largest ``b_osc`` (T) the coils can add to ``b_static`` within their ratings."""
        left = self.current_limit - np.abs(self._per_tesla_xy @ b_static + self._i_clamp)
        carry = self._osc_carry
        return max(0.0, float((left[carry] / self._per_tesla_osc[carry]).min()))


@dataclass(frozen=True)
class RigLimits:
    """Safety limits enforced by the server (reject) and by the client (clip).

    Attributes
    ----------
    b_static_max, b_osc_max : float
        Largest accepted ‖b_static‖ and b_osc, T.
    freq_max : float
        Largest accepted frequency, 1/s (the smallest is 0).
    coils : CoilMap
        The actuator's allocation; every coil's peak current must stay within its rating.
    """

    b_static_max: float
    b_osc_max: float
    freq_max: float
    coils: CoilMap

    @classmethod
    def from_params(cls, rig: Params | None = None, coils=None) -> RigLimits:
        """Field limits from ``models/rig.toml`` [limits], current limits and allocation from
        ``models/coils.toml`` (or the given :class:`~magctl.plant.coils.CoilSet`)."""
        rig = rig or load_model("rig")
        lim = rig.limits
        return cls(lim.b_static_max, lim.b_osc_max, lim.freq_max, CoilMap.from_coils(coils))

    def currents(self, cmd: Command) -> np.ndarray:
        return self.coils.currents(cmd.b_static[None, :], np.array([cmd.b_osc]))[0]

    def check(self, cmd: Command) -> np.ndarray:
        """Raise :class:`CommandRejected` naming the violated limit; return the coils' peak currents."""
        tol = 1e-12
        if not (np.all(np.isfinite(cmd.b_static)) and math.isfinite(cmd.b_osc) and math.isfinite(cmd.freq)):
            raise CommandRejected(f"command is not finite: b_static={cmd.b_static}, b_osc={cmd.b_osc}, freq={cmd.freq}")
        bmag = math.hypot(*cmd.b_static)
        if bmag > self.b_static_max * (1 + 1e-9) + tol:
            raise CommandRejected(
                f"|b_static| = {bmag * 1e3:.4g} mT exceeds the limit {self.b_static_max * 1e3:.4g} mT")
        if not 0.0 <= cmd.b_osc <= self.b_osc_max * (1 + 1e-9) + tol:
            raise CommandRejected(f"b_osc = {cmd.b_osc * 1e3:.4g} mT is outside [0, {self.b_osc_max * 1e3:.4g}] mT")
        if not 0.0 <= cmd.freq <= self.freq_max * (1 + 1e-9):
            raise CommandRejected(f"freq = {cmd.freq:.4g} Hz is outside [0, {self.freq_max:.4g}] Hz")
        cur = self.currents(cmd)
        over = cur - self.coils.current_limit * (1 + 1e-9)
        if np.any(over > 0):
            k = int(np.argmax(over))
            raise CommandRejected(
                f"coil {self.coils.names[k]} current {cur[k]:.4g} A exceeds its limit "
                f"{self.coils.current_limit[k]:.4g} A"
            )
        return cur

    def clip(self, cmd: Command) -> Command:
        """The nearest command within the limits: field magnitudes scaled down, frequency clipped.

        The static field is scaled (direction kept) into the field and current limits; the
        oscillation then gets at most the current the coils have left.
        """
        bs = cmd.b_static
        bmag = math.hypot(*bs)
        scale = 1.0
        if bmag > self.b_static_max:
            scale = self.b_static_max / bmag
        # a hair inside the ratings so that rounding never turns a clipped command into a rejected one
        scale = min(scale, self.coils.static_headroom(bs) * (1 - 1e-9))
        bs = bs * scale
        bo_max = min(self.b_osc_max, self.coils.osc_headroom(bs) * (1 - 1e-9))
        return Command(bs, min(max(cmd.b_osc, 0.0), bo_max), min(max(cmd.freq, 0.0), self.freq_max))


class Rig:
    """Base class of rig implementations: the lifecycle and its checks.

    Subclasses implement ``_configure``, ``_activate``, ``_deactivate``,
    ``_read``, ``_write``, ``_zero`` and ``_close``. Any exception raised by
    them in ``read``/``write``/``activate`` zeroes the coils and leaves the rig
    inactive (or in ``error`` if the coils could not be zeroed).

    Attributes
    ----------
    state : Lifecycle
        Current lifecycle state.
    activation : int
        Number of activations so far; the runtime resets the controller when it changes.
    last_error : str or None
        Message of the last error.
    limits : RigLimits
        Limits this side enforces (clipping happens in the runtime; ``write`` rejects).
    n_spheres : int
        Number of tracked spheres (set by ``configure``).
    """

    def __init__(self, limits: RigLimits | None = None):
        self.state = Lifecycle.UNCONFIGURED
        self.activation = 0
        self.last_error: str | None = None
        self.limits = limits or RigLimits.from_params()
        self.n_spheres = 0

    # --- lifecycle ------------------------------------------------------------------------------
    def configure(self) -> None:
        """unconfigured → inactive."""
        self._require(Lifecycle.UNCONFIGURED, "configure")
        self._guard(self._configure)
        self.state = Lifecycle.INACTIVE

    def activate(self) -> None:
        """inactive → active (explicit, also after an error)."""
        self._require(Lifecycle.INACTIVE, "activate")
        self._guard(self._activate)
        self.state = Lifecycle.ACTIVE
        self.activation += 1
        self.last_error = None

    def deactivate(self) -> None:
        """active → inactive, coils zeroed."""
        if self.state is Lifecycle.INACTIVE:
            return
        self._require(Lifecycle.ACTIVE, "deactivate")
        self._guard(self._deactivate)
        self.state = Lifecycle.INACTIVE

    def read(self) -> Observation:
        """Latest observation (inactive or active)."""
        if self.state in (Lifecycle.UNCONFIGURED, Lifecycle.ERROR):
            raise RigStateError(f"cannot read: rig is {self.state.value}")
        return self._guard(self._read)

    def write(self, cmd: Command) -> None:
        """Send a field command; only when active. Out-of-limit commands raise :class:`CommandRejected`."""
        if self.state is not Lifecycle.ACTIVE:
            raise RigStateError(f"cannot write: rig is {self.state.value} (activate it first)")
        self._guard(lambda: (self.limits.check(cmd), self._write(cmd)))

    def close(self) -> None:
        """Zero the coils (best effort) and release resources."""
        try:
            if self.state is Lifecycle.ACTIVE:
                self._zero()
        except Exception:  # noqa: BLE001 - closing must not raise
            pass
        finally:
            self._close()
            self.state = Lifecycle.UNCONFIGURED

    def fail(self, message: str) -> None:
        """Record an error: zero the coils and go inactive (or error if zeroing fails)."""
        self.last_error = message
        if self.state is Lifecycle.UNCONFIGURED:
            return
        try:
            self._zero()
            self.state = Lifecycle.INACTIVE
        except Exception as err:  # noqa: BLE001 - any failure to zero is terminal
            self.last_error = f"{message}; zeroing the coils failed too: {err}"
            self.state = Lifecycle.ERROR

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- helpers --------------------------------------------------------------------------------
    def _require(self, expected: Lifecycle, op: str) -> None:
        if self.state is not expected:
            raise RigStateError(f"cannot {op}: rig is {self.state.value}, needs {expected.value}")

    def _guard(self, fn):
        try:
            return fn()
        except RigError as err:
            self.fail(str(err))
            raise
        except Exception as err:
            self.fail(f"{type(err).__name__}: {err}")
            raise RigError(f"rig failed: {type(err).__name__}: {err}") from err

    # --- to implement ---------------------------------------------------------------------------
    def _configure(self) -> None:
        raise NotImplementedError

    def _activate(self) -> None:
        raise NotImplementedError

    def _deactivate(self) -> None:
        self._zero()

    def _read(self) -> Observation:
        raise NotImplementedError

    def _write(self, cmd: Command) -> None:
        raise NotImplementedError

    def _zero(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        pass
