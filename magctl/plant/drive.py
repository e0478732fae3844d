"""The drive: commanded (speed, heading) → field command, the inverse of coils + robot.

The in-plane field points along the commanded heading at the nominal magnitude
``B_0``; the rocking amplitude is the nominal ``b_osc``; the speed is set by the
frequency. The drive inverts the steady stick-slip speed ``v(f)``
(:func:`magctl.plant._stickslip.speed` of the field the coils deliver,
:meth:`magctl.plant.coils.CoilActuator.deliver`) on its rising
branch ``0 ≤ f ≤ f_peak`` by interpolating a table computed once from the same
parameters. Commanded speeds are clipped to ``[0, v_max]``; zero speed turns
the oscillation off and keeps the aligning field.

The drive's and the fused :class:`ActuatedRobot`'s behaviour is their kernels in :mod:`magctl.plant.kernels`,
run by both engines; the numpy forms they are tested against are in ``tests/reference/plant_blocks.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import load_model, require
from magctl.core.block import Block, StateVar, substate
from magctl.core.diagram import Diagram
from magctl.core.errors import ParameterError
from magctl.core.kernel import Kernel
from magctl.core.ports import Port
from magctl.plant._coilfield import CoilSet, load_coils
from magctl.plant._stickslip import StickSlipParams, load_robot, speed
from magctl.plant.coils import CoilActuator
from magctl.plant.robot import StickSlipRobot

__all__ = ["Drive", "DriveSettings", "actuated_robot", "delivered_speed_curve", "load_drive"]


@dataclass(frozen=True)
class DriveSettings:
    """Nominal field command (``models/robot.toml`` ``[drive]``), SI.

    Attributes
    ----------
    static_field : float
        ``B_0``, in-plane aligning field, T.
    osc_field : float
        Rocking field amplitude, T.
    nominal_speed : float
        The paper's operating speed, m/s (§IV-C: 0.4 mm/s).
    max_speed : float
        Highest speed the drive commands, m/s.
    """

    static_field: float
    osc_field: float
    nominal_speed: float
    max_speed: float


def load_drive(name: str = "robot") -> DriveSettings:
    """Read the ``[drive]`` table of ``models/<name>.toml``."""
    p = load_model(name)
    if "drive" not in p:
        raise ParameterError(f"{p._path}: missing [drive] table")
    d = p.drive
    require(d, "static_field", "osc_field", "nominal_speed", "max_speed")
    vals = DriveSettings(float(d.static_field), float(d.osc_field), float(d.nominal_speed), float(d.max_speed))
    for k, v in vars(vals).items():
        if not v > 0:
            raise ParameterError(f"{p._path}:drive.{k}: value {v!r} must be positive")
    return vals


def delivered_speed_curve(robot: StickSlipParams, coils: CoilSet, static_field: float, osc_field: float,
                          freqs) -> tuple[np.ndarray, np.ndarray]:
    """Steady speed (m/s) and delivered ``b_osc`` (T) versus frequency for a command along +x.

    Combines the coils' voltage/current limits (attenuation of ``b_osc``) and the
    robot's own rocking lag; used by the drive's inverse and by the actuator study.
    """
    freqs = np.asarray(freqs, dtype=float)
    n = freqs.size
    b_s, b_osc, _ = CoilActuator("coils", coils).deliver(np.tile([static_field, 0.0], (n, 1)),
                                                       np.full(n, osc_field), freqs)
    return speed(robot, np.hypot(b_s[:, 0], b_s[:, 1]), b_osc, freqs), b_osc


class Drive(Block):
    """Speed and heading → field command, stateless and vectorised.

    Ports (docs/interfaces.md): inputs ``speed`` () m/s, ``heading`` () rad;
    outputs ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s.

    Parameters
    ----------
    name : str
    robot : StickSlipParams, optional
    coils : CoilSet, optional
    settings : DriveSettings, optional
        Defaults read ``models/robot.toml``, ``models/coils.toml``, ``models/fluid.toml``.
    dt : float
    """

    def __init__(self, name: str = "drive", robot: StickSlipParams | None = None, coils: CoilSet | None = None,
                 settings: DriveSettings | None = None, *, dt: float = FRAME_PERIOD_S):
        self.robot = load_robot() if robot is None else robot
        self.coils = load_coils() if coils is None else coils
        self.settings = load_drive() if settings is None else settings
        super().__init__(
            name,
            inputs=[Port("speed", (), "m/s"), Port("heading", (), "rad")],
            outputs=[Port("b_static", (2,), "T"), Port("b_osc", (), "T"), Port("freq", (), "1/s")],
            dt=dt, feedthrough=True,
        )
        s = self.settings
        f = np.linspace(0.0, 2000.0, 40001)
        v, _ = delivered_speed_curve(self.robot, self.coils, s.static_field, s.osc_field, f)
        k = int(np.argmax(v))
        self.peak_freq, self.peak_speed = float(f[k]), float(v[k])
        if self.peak_speed < s.max_speed:
            raise ParameterError(
                f"drive: max_speed {s.max_speed * 1e3:.3g} mm/s exceeds the model's peak speed "
                f"{self.peak_speed * 1e3:.3g} mm/s at {self.peak_freq:.3g} Hz (models/robot.toml [drive])"
            )
        # rising branch from the first frequency that moves the robot; strictly increasing there
        moving = np.nonzero(v[: k + 1] > 0)[0]
        j0 = max(int(moving[0]) - 1, 0)
        self._v_table = np.maximum.accumulate(v[j0: k + 1])
        self._f_table = f[j0: k + 1]
        self.nominal_freq = self.frequency_for(s.nominal_speed)

    def frequency_for(self, speed) -> np.ndarray:
        """Field frequency (Hz) commanding ``speed`` (m/s), clipped to ``[0, max_speed]``; 0 for speed 0
        (the block's ``freq`` output, shaped like ``speed``)."""
        sp = np.asarray(speed, dtype=float)
        flat = sp.reshape(-1)
        out, _ = self.step({}, {"speed": flat, "heading": np.zeros(flat.shape)})
        return out["freq"].reshape(sp.shape)

    def kernel_params(self) -> tuple:
        """The parameters of :func:`magctl.plant.kernels.drive_command` (the inverse speed table, limits, fields)."""
        s = self.settings
        return (np.ascontiguousarray(self._v_table), np.ascontiguousarray(self._f_table), float(s.max_speed),
                float(s.static_field), float(s.osc_field))

    def kernel(self):
        from magctl.plant import kernels as k

        return Kernel(step=k.drive_step, params=self.kernel_params())


def actuated_robot(name: str = "plant", *, position=(0.0, 0.0), heading=0.0, variability: bool = True,
                   robot: StickSlipParams | None = None, coils: CoilSet | None = None,
                   settings: DriveSettings | None = None, dt: float = FRAME_PERIOD_S) -> Diagram:
    """Drive → coils → robot as one diagram: inputs ``speed``, ``heading``; outputs the robot's ports and
    ``saturated``. Blocks are named ``drive``, ``coils``, ``robot``."""
    robot = load_robot() if robot is None else robot
    coils = load_coils() if coils is None else coils
    drive = Drive("drive", robot, coils, settings, dt=dt)
    act = CoilActuator("coils", coils, dt=dt)
    bot = StickSlipRobot("robot", robot, position=position, heading=heading, variability=variability, dt=dt)
    return Diagram(
        name, [drive, act, bot],
        connections=[("drive.b_static", "coils.b_static"), ("drive.b_osc", "coils.b_osc"),
                     ("drive.freq", "coils.freq"),
                     ("coils.b_static_delivered", "robot.b_static_delivered"),
                     ("coils.b_osc_delivered", "robot.b_osc_delivered"),
                     ("coils.freq_delivered", "robot.freq_delivered")],
        inputs={"speed": "drive.speed", "heading": "drive.heading"},
        outputs={"position": "robot.position", "heading": "robot.heading", "velocity": "robot.velocity",
                 "tilt": "robot.tilt", "saturated": "coils.saturated"},
        dt=dt,
    )


class ActuatedRobot(Block):
    """Drive → coils → robot fused into one block: the cheap path for batched Monte Carlo.

    Same physics as :func:`actuated_robot` (its kernel runs the three blocks' kernel functions in a row)
    with one block call per step instead of three. Inputs ``speed`` () m/s, ``heading`` () rad;
    outputs the robot's ``position``, ``heading``, ``velocity``, ``tilt`` and the coils'
    ``saturated`` of the previous frame, all from the state (no feedthrough).
    """

    def __init__(self, name: str = "plant", *, position=(0.0, 0.0), heading=0.0, variability: bool = True,
                 robot: StickSlipParams | None = None, coils: CoilSet | None = None,
                 settings: DriveSettings | None = None, dt: float = FRAME_PERIOD_S):
        robot = load_robot() if robot is None else robot
        coils = load_coils() if coils is None else coils
        self.drive = Drive("drive", robot, coils, settings, dt=dt)
        self.coils = CoilActuator("coils", coils, dt=dt)
        self.robot = StickSlipRobot("robot", robot, position=position, heading=heading,
                                    variability=variability, dt=dt)
        super().__init__(
            name, inputs=list(self.drive.inputs.values()),
            outputs=[*self.robot.outputs.values(), self.coils.outputs["saturated"]],
            dt=dt, feedthrough=False,
        )

    @property
    def uses_random(self) -> bool:
        return self.robot.uses_random

    def state_vars(self):
        return (substate("coils", self.coils.state_vars(), "the coils' state"),
                substate("robot", self.robot.state_vars(), "the robot's state"),
                StateVar("saturated", (), "bool", description="the coils saturated in the previous frame"))

    def initial_state(self, batch, rng=None):
        return {"coils": self.coils.initial_state(batch), "robot": self.robot.initial_state(batch, rng),
                "saturated": np.zeros(batch, dtype=bool)}

    def set_pose(self, state, position=None, heading=None):
        """A copy of ``state`` with the robot at ``position`` and ``heading`` (see :meth:`StickSlipRobot.set_pose`)."""
        return {**state, "robot": self.robot.set_pose(state["robot"], position, heading)}

    def kernel(self):
        from magctl.plant import kernels as k

        params = (*self.drive.kernel_params(), *self.coils.kernel_params(), *self.robot.kernel_params())
        if self.robot.cv > 0:
            return Kernel(output=k.actuated_output, update=k.actuated_update_noisy, params=params,
                          stream="robot.rng")
        return Kernel(output=k.actuated_output, update=k.actuated_update, params=params)
