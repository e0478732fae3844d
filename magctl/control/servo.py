"""PI visual servo: drive the robot to a target point by speed and heading (paper §II, §VI-A).

The law acts on the planar error vector ``e = target − robot_est``::

    u[k] = Kp·e[k] + Ki·I[k]              (velocity command, m/s)
    speed = min(‖u‖, v_cap),  heading = atan2(u_y, u_x)
    I[k+1] = I[k] + T·e[k]

With ``anti_windup`` (conditional integration) ``I`` is held while ``‖u‖ > v_cap``.
Without it — the paper's "basic" PI — ``I`` integrates all the time and is only
clamped to ``Ki·‖I‖ ≤ v_cap``: during a long approach at the constant (saturated)
speed the integral fills up, and it must be emptied by running past the target.
Together with the camera lag this gives an overshoot of about
``v_cap/Kp + v_cap·d·T`` whatever the step length, the ~100 µm of §VI-A.

So along the line to the target it is the single-axis loop that
:mod:`magctl.stability.servo` analyses. ``v_cap`` is the lower of the
parameter ``speed_max`` and the optional ``speed_cap`` input (push tasks push
slowly). With ``constant_speed`` the robot runs at ``v_cap`` until it arrives,
as in the paper's experiments (§VI-A). Inside ``arrive_tol`` the speed is zero
and ``arrived`` is true; a non-finite estimate or the optional ``hold`` input
(wire the tracker's ``lost``) also stops the robot and freezes the integral.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.config import Params, load_model
from magctl.core.block import Block, StateVar
from magctl.core.errors import ParameterError
from magctl.core.ports import DIMENSIONLESS, Port


def servo_settings() -> list[str]:
    """Names of the servo settings in ``models/servo.toml`` (``"paper"``, ``"tuned"``)."""
    return sorted(k for k in load_model("servo") if k != "choice")


def default_servo_setting() -> str:
    """The setting every controller uses unless told otherwise (``models/servo.toml`` ``[choice] default``)."""
    return str(load_model("servo").choice.default)


def servo_params(setting: str | None = None) -> Params:
    """The ``[setting]`` table of ``models/servo.toml``; None gives :func:`default_servo_setting`."""
    model = load_model("servo")
    name = default_servo_setting() if setting is None else setting
    if name == "choice" or name not in model:
        raise ParameterError(f"models/servo.toml: no servo setting [{name}]; settings: {servo_settings()}")
    return model[name]


class Servo(Block):
    """PI visual servo block.

    Parameters
    ----------
    name : str
        Block name.
    kp : float
        Proportional gain in 1/s ((m/s) of speed per m of error).
    ki : float
        Integral gain in 1/s².
    speed_max : float
        Speed limit in m/s (paper: ~400 µm/s).
    arrive_tol : float
        Distance in m under which the robot has arrived and stops.
    anti_windup : bool
        Conditional integration (hold ``I`` while saturated); otherwise ``Ki·‖I‖`` is clamped at the speed limit.
    constant_speed : bool
        Run at the speed limit whenever not arrived (direction from the PI law).
    speed_cap_input : bool
        Add an input ``speed_cap`` () m/s; the effective limit is ``min(speed_max, speed_cap)``.
    hold_input : bool
        Add an input ``hold`` () bool that stops the robot (e.g. the tracker's ``lost``).
    params : Params, optional
        A table from :func:`servo_params`; explicit keyword values override it.

    Ports
    -----
    inputs: ``target`` (2,) m, ``robot_est`` (2,) m [, ``speed_cap`` () m/s] [, ``hold`` () bool]
    outputs: ``speed`` () m/s, ``heading`` () rad, ``arrived`` () bool, ``saturated`` () bool
    """

    def __init__(self, name: str = "servo", *, kp: float | None = None, ki: float | None = None,
                 speed_max: float | None = None, arrive_tol: float | None = None, anti_windup: bool | None = None,
                 constant_speed: bool = False,
                 speed_cap_input: bool = False, hold_input: bool = False, params: Params | None = None,
                 dt: float = FRAME_PERIOD_S):
        if params is None and None in (kp, ki, speed_max, arrive_tol, anti_windup):
            params = servo_params()
        self.anti_windup = bool(params.anti_windup if anti_windup is None else anti_windup)
        self.kp = float(params.kp if kp is None else kp)
        self.ki = float(params.ki if ki is None else ki)
        self.speed_max = float(params.speed_max if speed_max is None else speed_max)
        self.arrive_tol = float(params.arrive_tol if arrive_tol is None else arrive_tol)
        for label, v, lo in (("kp", self.kp, 0.0), ("ki", self.ki, 0.0), ("speed_max", self.speed_max, 0.0),
                             ("arrive_tol", self.arrive_tol, 0.0)):
            if not np.isfinite(v) or v < lo or (label in ("kp", "speed_max") and v == 0):
                raise ParameterError(f"servo {name!r}: {label}={v!r} must be finite and "
                                     f"{'positive' if label in ('kp', 'speed_max') else 'non-negative'}")
        self.constant_speed = bool(constant_speed)
        ins = [Port("target", (2,), "m"), Port("robot_est", (2,), "m")]
        if speed_cap_input:
            ins.append(Port("speed_cap", (), "m/s"))
        if hold_input:
            ins.append(Port("hold", (), DIMENSIONLESS, "bool"))
        outs = [Port("speed", (), "m/s"), Port("heading", (), "rad"), Port("arrived", (), DIMENSIONLESS, "bool"),
                Port("saturated", (), DIMENSIONLESS, "bool")]
        super().__init__(name, inputs=ins, outputs=outs, dt=dt, feedthrough=True)

    def state_vars(self):
        return (StateVar("I", (2,), symbol="I", description="integral of the error, m·s"),
                StateVar("heading", (), symbol="ψ_c", description="last commanded heading (kept at zero command), rad"))

    def initial_state(self, batch, rng=None):
        return {"I": np.zeros((batch, 2)), "heading": np.zeros(batch)}

    def kernel(self):
        """The compiled law (:func:`magctl.control.kernels.servo_step` and its variants by optional inputs)."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        step = {(False, False): k.servo_step, (True, False): k.servo_cap_step, (False, True): k.servo_hold_step,
                (True, True): k.servo_cap_hold_step}[("speed_cap" in self.inputs, "hold" in self.inputs)]
        return Kernel(step=step, params=(self.kp, self.ki, self.speed_max, self.arrive_tol, self.anti_windup,
                                         self.constant_speed, float(self.dt)))
