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
"""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.batched import rows_times
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
        self._p_z = self.pinv[:, 2].copy()
        self._A_xy = np.ascontiguousarray(self.A[:2].T)  # (6, 2): currents → (B_x, B_y)
        self._vmax_over_r = self.coils.voltage_limit / R
        self._vclip = bool(np.any(self.coils.current_limit > self._vmax_over_r))
        self._inv_imax = 1.0 / self.coils.current_limit
        pz = np.abs(self._p_z)
        zc = np.nonzero(pz > 1e-9 * pz.max())[0]
        # a slice when the oscillating coils are adjacent in the file (cheaper than fancy indexing)
        contiguous = np.array_equal(zc, np.arange(zc[0], zc[-1] + 1))
        self._zc = slice(int(zc[0]), int(zc[-1]) + 1) if contiguous else zc
        self._imax_min = float(self.coils.current_limit.min())
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
        zc = np.arange(self.pinv.shape[0])[self._zc]
        a = self.allocation
        return (a.per_tesla_xy, a.clamp_currents, self.coils.current_limit, self._inv_imax, zc.astype(np.int64),
                self._imax_z, self._vmax_z, self._r_z, self._r2, self._two_pi_l, self._inv_pz, self._vclip,
                np.broadcast_to(self._vmax_over_r, self.decay.shape), self.avg_weight, self.decay, self._A_xy)

    def kernel(self):
        from magctl.plant import kernels as k

        return Kernel(step=k.coils_step, params=self.kernel_params())

    def deliver(self, b_static, b_osc, freq):
        """Steady-state delivered field for a command held long enough for the RL transients to end.

        Returns ``(b_static_delivered (B, 2), b_osc_delivered (B,), saturated (B,))``; the same
        limits as the block, used for speed curves and the drive's inverse.
        """
        u = {"b_static": np.atleast_2d(np.asarray(b_static, float)), "b_osc": np.atleast_1d(np.asarray(b_osc, float)),
             "freq": np.atleast_1d(np.asarray(freq, float))}
        i_s, _, s_osc, _, sat = self._solve({"i": 0.0}, u)
        return rows_times(i_s, self._A_xy), u["b_osc"] * s_osc, sat

    def _solve(self, state, u):
        # hot path: one vectorised op per line; see the module docstring for the steps
        i_s = self.allocation.static_currents(u["b_static"])
        ai = np.abs(i_s)
        s_static = None
        if ai.max() > self._imax_min and (ai > self.coils.current_limit).any():
            s_static = 1.0 / np.maximum((ai * self._inv_imax).max(axis=1), 1.0)
            i_s *= s_static[:, None]
            ai *= s_static[:, None]
        # oscillation: only the coils that carry it (|A⁺ row| > 0); s = min(1, cap / |b_osc|)
        freq = np.maximum(u["freq"], 0.0)
        az = ai[:, self._zc]
        w = freq[:, None] * self._two_pi_l
        z = np.sqrt(self._r2 + w * w)
        cap = np.minimum(self._imax_z - az, (self._vmax_z - self._r_z * az) / z)
        cap *= self._inv_pz
        cap_min = cap[:, 0]
        for c in range(1, cap.shape[1]):
            cap_min = np.minimum(cap_min, cap[:, c])
        s_osc = np.minimum(cap_min / np.maximum(np.abs(u["b_osc"]), 1e-300), 1.0)
        if self._vclip:
            i_s = np.clip(i_s, -self._vmax_over_r, self._vmax_over_r)
        i_avg = i_s + (state["i"] - i_s) * self.avg_weight
        sat = s_osc < 1.0 - 1e-12
        if s_static is not None:
            sat |= s_static < 1.0
        return i_s, i_avg, s_osc, freq, sat

    def step(self, state, u):
        # the allocation and limits are solved once per frame for both the outputs and the next current
        i_s, i_avg, s_osc, freq, sat = self._solve(state, u)
        out = {
            "currents": i_avg,
            "b_static_delivered": rows_times(i_avg, self._A_xy),
            "b_osc_delivered": u["b_osc"] * s_osc,
            "freq_delivered": freq,
            "saturated": sat,
        }
        return out, {"i": i_s + (state["i"] - i_s) * self.decay}

    def output(self, state, u):
        return self.step(state, u)[0]

    def update(self, state, u):
        i_s = self._solve(state, u)[0]
        return {"i": i_s + (state["i"] - i_s) * self.decay}
