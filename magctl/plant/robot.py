"""The stick-slip robot block: delivered field → pose, velocity and tilt at the frame rate.

Per frame of length ``h`` with the delivered field held (docs/plant-actuator.md):

* **Heading** follows the in-plane field direction ``ψ_B``: ``ζ ψ̇ = −m|B| sin(ψ − ψ_B)``,
  solved exactly, ``tan(e(t)/2) = tan(e₀/2) e^{−t/τ_ψ}`` with ``e = ψ − ψ_B`` and
  ``τ_ψ = ζ / (m|B|)``.
* **Translation** along the heading at the stick-slip speed ``v = f·s(θ_a)``
  (:mod:`magctl.plant._stickslip`), times ``max(0, 1 + c_v n)`` with ``n ~ N(0, 1)``
  per frame when ``step_cv > 0``. The displacement integrates the turning heading
  over the frame by Simpson's rule (start, middle, end).
* **Tilt** is the cycle-mean pitch ``(2/π) θ_a`` that the fluid model uses (paper §IV-C
  models the robot at a fixed ``π/8``).

The outputs are the state at the start of the frame, so the block has no feedthrough. The block's
behaviour is its kernel (:func:`magctl.plant.kernels.robot_advance`), run by both engines; the numpy form it
is tested against is ``RefStickSlipRobot`` in ``tests/reference/plant_blocks.py``.
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.errors import WiringError
from magctl.core.kernel import Kernel
from magctl.core.ports import Port
from magctl.plant._stickslip import (
    StickSlipParams,
    heading_rate,
    load_robot,
    rocking_amplitude,
    speed,
    step_length,
)

__all__ = ["StickSlipParams", "StickSlipRobot", "load_robot", "rocking_amplitude", "speed", "step_length"]


# The ports every robot block shares (the stick-slip model and the rig's stand-in): the field the
# coils deliver in, the pose and what the fluid model needs out (docs/interfaces.md).
ROBOT_INPUTS = (Port("b_static_delivered", (2,), "T"), Port("b_osc_delivered", (), "T"),
                Port("freq_delivered", (), "1/s"))
ROBOT_OUTPUTS = (Port("position", (2,), "m"), Port("heading", (), "rad"), Port("velocity", (2,), "m/s"),
                 Port("tilt", (), "rad"))


class StickSlipRobot(Block):
    """Mag-µBot on glass under oil, driven by the delivered coil field.

    Ports (docs/interfaces.md): inputs ``b_static_delivered`` (2,) T,
    ``b_osc_delivered`` () T, ``freq_delivered`` () 1/s; outputs ``position`` (2,) m,
    ``heading`` () rad, ``velocity`` (2,) m/s (mean over the previous frame),
    ``tilt`` () rad.

    Parameters
    ----------
    name : str
    params : StickSlipParams, optional
        Defaults to ``load_robot()`` (``models/robot.toml`` and ``models/fluid.toml``).
    position : array_like, (2,) or (B, 2)
        Initial position(s), m; per-trial arrays must match the batch.
    heading : float or array_like (B,)
        Initial heading(s), rad.
    variability : bool
        Draw the per-frame step variation (``params.step_cv``); False makes the block deterministic.
    dt : float
        Frame period, s.
    """

    def __init__(self, name: str = "robot", params: StickSlipParams | None = None, *, position=(0.0, 0.0),
                 heading=0.0, variability: bool = True, dt: float = FRAME_PERIOD_S):
        self.params = load_robot() if params is None else params
        self.position = np.asarray(position, dtype=float)
        self.heading = np.asarray(heading, dtype=float)
        self.cv = self.params.step_cv if variability else 0.0
        super().__init__(
            name,
            inputs=list(ROBOT_INPUTS),
            outputs=list(ROBOT_OUTPUTS),
            dt=dt, feedthrough=False,
        )
        p = self.params
        self._half_rate = -0.5 * dt * p.moment / p.turn_drag  # −(h/2)/τ_ψ per tesla
        self._pitch_c = 2.0 * np.pi * p.pitch_drag_ratio * p.turn_drag / p.moment  # ωτ_θ·|B| per hertz
        self._cos0 = float(np.cos(p.break_angle))
        self._eta_l = p.slip_efficiency * p.length
        self._simpson = np.array([1.0, 4.0, 1.0]) / 6.0

    @property
    def uses_random(self) -> bool:
        return self.cv > 0

    # --- state ---------------------------------------------------------------------------
    def state_vars(self):
        return (StateVar("pos", (2,), symbol="p", description="position, m"),
                StateVar("psi", (), symbol="ψ", description="heading, rad"),
                StateVar("vel", (2,), symbol="v̄", description="mean velocity over the previous frame, m/s"),
                StateVar("tilt", (), symbol="θ̄", description="cycle-mean pitch (2/π)·θ_a, rad"),
                rng_var("per-frame step variation n ~ N(0, 1), read at position k"),
                StateVar("k", (), "int64", "k", "frames stepped (the stream position)", batched=False))

    def initial_state(self, batch, rng=None):
        state = {"pos": np.zeros((batch, 2)), "psi": np.zeros(batch), "vel": np.zeros((batch, 2)),
                 "tilt": np.zeros(batch), "rng": rng, "k": 0}
        return self.set_pose(state, self.position, self.heading)

    def set_pose(self, state, position=None, heading=None):
        """A copy of ``state`` with the robot placed at ``position`` (2,)/(B, 2) m and ``heading`` ()/(B,) rad."""
        batch = state["psi"].shape[0]
        new = dict(state)
        if position is not None:
            pos = np.asarray(position, dtype=float)
            if pos.shape not in ((2,), (batch, 2)):
                raise WiringError(f"block {self.name!r}: initial position must be (2,) or ({batch}, 2), "
                                  f"got {pos.shape}")
            new["pos"] = np.broadcast_to(pos, (batch, 2)).copy()
        if heading is not None:
            psi = np.asarray(heading, dtype=float)
            if psi.shape not in ((), (batch,)):
                raise WiringError(f"block {self.name!r}: initial heading must be a scalar or ({batch},), "
                                  f"got {psi.shape}")
            new["psi"] = np.broadcast_to(psi, (batch,)).copy()
        new["vel"] = np.zeros((batch, 2))
        return new

    # --- behaviour -----------------------------------------------------------------------
    def kernel_params(self) -> tuple:
        """The parameters of :func:`magctl.plant.kernels.robot_advance`."""
        return (self.dt, self._half_rate, self._pitch_c, self._cos0, self._eta_l, self._simpson, float(self.cv))

    def kernel(self):
        from magctl.plant import kernels as k

        if self.cv > 0:
            return Kernel(output=k.robot_output, update=k.robot_update_noisy, params=self.kernel_params(),
                          stream="rng")
        return Kernel(output=k.robot_output, update=k.robot_update, params=self.kernel_params())


def steady_speed(params: StickSlipParams, b_xy, b_osc, freq) -> np.ndarray:
    """Stick-slip speed (m/s) the robot settles to for a constant delivered field; see :func:`speed`."""
    return speed(params, b_xy, b_osc, freq)


def heading_time_constant(params: StickSlipParams, b_xy) -> np.ndarray:
    """``τ_ψ = ζ / (m |B_xy|)`` (s)."""
    return 1.0 / heading_rate(params, b_xy)
