"""The six-coil field actuator: field command → coil currents → the field the robot gets.

Three steps each frame (docs/plant-actuator.md):

1. **Allocation.** The actuation matrix ``A`` (4×6, from the coil geometry with
   magpylib, :mod:`magctl.plant._coilfield`) maps currents to
   ``[B_x, B_y, B_z, ∂B_z/∂z]`` at the workspace centre. The static command
   ``[b_x, b_y, 0, G_clamp]`` and the oscillation command ``[0, 0, b_osc, 0]``
   get the least-squares (minimum-norm) currents ``i = A⁺ b``; ``A`` has full
   row rank, so these reproduce the command exactly when within limits.
2. **Limits.** Per coil ``|i_s| + |i_o| ≤ I_max`` (current) and
   ``R|i_s| + |Z(ω)||i_o| ≤ V_max`` (voltage, ``Z(ω) = R + jωL``): the static
   currents are scaled down first if they alone exceed ``I_max``, then the
   oscillation amplitude takes what current and voltage are left, which is how
   a voltage-limited current amplifier attenuates a fast waveform (amplitude
   ``∝ V/(ωL)`` once ``ωL ≫ R``). Scaling a whole current vector keeps the field
   direction, so the heading command survives saturation. Any scaling sets
   ``saturated``.
3. **RL dynamics.** The amplifier applies ``v = R·i_cmd`` (clipped to ``V_max``)
   for the static part, held over the frame; the coil current obeys
   ``L di/dt = v − R i``, discretised exactly:
   ``i[k+1] = e^{−h/τ} i[k] + (1 − e^{−h/τ}) v/R`` with ``τ = L/R``. The outputs
   are frame averages, ``ī = v/R + (i[k] − v/R)(τ/h)(1 − e^{−h/τ})``.

The block's behaviour is its kernel, :func:`magctl.plant.kernels.coils_step`, run by both engines; the
numpy form it is tested against is ``RefCoilActuator`` in ``tests/reference/plant_blocks.py``.
"""

from __future__ import annotations

import copy

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar
from magctl.core.kernel import Kernel
from magctl.core.ports import Port
from magctl.plant._coilfield import Coil, CoilAllocation, CoilSet, load_coils

__all__ = ["Coil", "CoilActuator", "CoilSet", "load_coils"]


class CoilActuator(Block):
    """Six coils turning a field command into the field the robot experiences.

    Ports (docs/interfaces.md): inputs ``b_static`` (2,) T, ``b_osc`` () T,
    ``freq`` () 1/s; outputs ``currents`` (6,) A (frame-average static
    currents), ``b_static_delivered`` (2,) T, ``b_osc_delivered`` () T (sine
    amplitude), ``freq_delivered`` () 1/s, ``saturated`` () bool.

    Parameters
    ----------
    name : str
    coils : CoilSet, optional
        Defaults to ``load_coils()`` (``models/coils.toml``).
    dt : float
        Frame period (s).
    """

    def __init__(self, name: str = "coils", coils: CoilSet | None = None, *, dt: float = FRAME_PERIOD_S):
        self.coils = load_coils() if coils is None else coils
        n = len(self.coils.coils)
        super().__init__(
            name,
            inputs=[Port("b_static", (2,), "T"), Port("b_osc", (), "T"), Port("freq", (), "1/s")],
            outputs=[Port("currents", (n,), "A"), Port("b_static_delivered", (2,), "T"),
                     Port("b_osc_delivered", (), "T"), Port("freq_delivered", (), "1/s"),
                     Port("saturated", (), "1", "bool")],
            dt=dt, feedthrough=True,
        )
        self.A = self.coils.actuation_matrix()
        self.allocation = CoilAllocation(np.linalg.pinv(self.A), self.coils.clamp_gradient)
        self.pinv = self.allocation.pinv
        R, L = self.coils.resistance, self.coils.inductance
        tau = L / R
        self.decay = np.exp(-dt / tau)
        # weight of the frame-start current in the frame-average current
        self.avg_weight = tau / dt * (1.0 - self.decay)
        self._A_xy = np.ascontiguousarray(self.A[:2].T)  # (6, 2): currents → (B_x, B_y)
        self._vmax_over_r = self.coils.voltage_limit / R
        self._vclip = bool(np.any(self.coils.current_limit > self._vmax_over_r))
        self._inv_imax = 1.0 / self.coils.current_limit
        pz = np.abs(self.pinv[:, 2])
        self._zc = np.nonzero(pz > 1e-9 * pz.max())[0].astype(np.int64)  # the coils that carry the oscillation
        self._inv_pz = 1.0 / pz[self._zc]
        self._imax_z = self.coils.current_limit[self._zc]
        self._vmax_z = self.coils.voltage_limit[self._zc]
        self._r_z = R[self._zc]
        self._r2 = R[self._zc] ** 2
        self._two_pi_l = 2.0 * np.pi * L[self._zc]

    def state_vars(self):
        return (StateVar("i", (len(self.coils.coils),), symbol="i", description="coil currents at the frame start, A"),)

    def initial_state(self, batch, rng=None):
        return {"i": np.zeros((batch, len(self.coils.coils)))}

    def kernel_params(self) -> tuple:
        """The parameters of :func:`magctl.plant.kernels.coil_field` (allocation, limits, RL weights)."""
        a = self.allocation
        return (a.per_tesla_xy, a.clamp_currents, self.coils.current_limit, self._inv_imax, self._zc,
                self._imax_z, self._vmax_z, self._r_z, self._r2, self._two_pi_l, self._inv_pz, self._vclip,
                np.broadcast_to(self._vmax_over_r, self.decay.shape), self.avg_weight, self.decay, self._A_xy)

    def kernel(self):
        from magctl.plant import kernels as k

        return Kernel(step=k.coils_step, params=self.kernel_params())

    def deliver(self, b_static, b_osc, freq):
        """Steady-state delivered field for a command held long enough for the RL transients to end.

        Returns ``(b_static_delivered (B, 2), b_osc_delivered (B,), saturated (B,))``; the same
        limits as the block, used for speed curves and the drive's inverse. One step of the block's
        kernel with the transients over (:meth:`_settled`), from rest.
        """
        b_static = np.atleast_2d(np.asarray(b_static, float))
        b_osc, freq = np.atleast_1d(np.asarray(b_osc, float)), np.atleast_1d(np.asarray(freq, float))
        batch = np.broadcast_shapes(b_static.shape[:1], b_osc.shape, freq.shape)[0]
        u = {"b_static": np.broadcast_to(b_static, (batch, 2)), "b_osc": np.broadcast_to(b_osc, (batch,)),
             "freq": np.broadcast_to(freq, (batch,))}
        out, _ = self._settled().step(self.initial_state(batch), u)
        return out["b_static_delivered"], out["b_osc_delivered"], out["saturated"]

    def _settled(self) -> CoilActuator:
        """This actuator with its RL transients over: each frame's currents are the amplifier's targets
        ``v/R`` (the weights of the frame-start current in the frame average and in the next current are 0,
        the limit ``h/τ → ∞``). Built once."""
        steady = self.__dict__.get("_settled_copy")
        if steady is None:
            steady = copy.copy(self)
            steady.__dict__.pop("_settled_copy", None)
            steady.decay = np.zeros_like(self.decay)
            steady.avg_weight = np.zeros_like(self.avg_weight)
            self.__dict__["_settled_copy"] = steady
        return steady
