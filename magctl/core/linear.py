"""Discrete linear blocks that export themselves to python-control.

Each block's :meth:`to_control` returns a ``control.StateSpace`` with the
block's ``dt``; inputs and outputs are the ports' elements in declaration
order (a port of shape ``(2,)`` contributes two signals).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar, as_batch
from magctl.core.checks import check_finite, check_positive
from magctl.core.errors import MagctlError, WiringError
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port


def _ss(*args, **kwargs):
    """``control.ss``, imported on first use (python-control and scipy take a second to import)."""
    import control

    return control.ss(*args, **kwargs)


def _size(shape) -> int:
    return int(np.prod(shape, dtype=int))


def _labels(name: str, shape) -> list[str]:
    """State names ``name[i]`` over a port's elements (``name`` for a scalar)."""
    return [f"{name}[{i}]" for i in range(_size(shape))] if tuple(shape) else [name]


class Constant(Block):
    """A constant (per-trial) source: ``y[k] = value``.

    Parameters
    ----------
    value : array_like
        Shape ``shape`` (same for every trial) or ``(B, *shape)`` (given per trial
        when the state is made).
    """

    def __init__(self, name: str, value, *, shape=(), unit: str = DIMENSIONLESS, dt: float = FRAME_PERIOD_S):
        super().__init__(name, outputs=[Port("y", tuple(shape), unit)], dt=dt, feedthrough=False)
        self.value = np.asarray(value, dtype=float)

    def state_vars(self):
        return (StateVar("y", self.outputs["y"].shape, symbol="c", description="the value, per trial"),)

    def initial_state(self, batch, rng=None):
        return {"y": as_batch(self.value, self.outputs["y"], batch)}

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(output=k.constant_output, update=k.no_update)

    def to_control(self):
        n = _size(self.outputs["y"].shape)
        return _ss(np.zeros((0, 0)), np.zeros((0, 0)), np.zeros((n, 0)), np.zeros((n, 0)), dt=self.dt)


class Gain(Block):
    """``y[k] = K u[k]``: a scalar gain, or a matrix acting on a vector port.

    Parameters
    ----------
    k : float or (m, n) array
        Gain. A scalar keeps the shape; a matrix maps shape ``(n,)`` to ``(m,)``.
    """

    def __init__(self, name: str, k, *, shape=(), in_unit: str = DIMENSIONLESS, out_unit: str | None = None,
                 dt: float = FRAME_PERIOD_S):
        self.k = np.asarray(k, dtype=float)
        if not np.all(np.isfinite(self.k)):
            raise MagctlError(f"Gain {name!r}: k={k!r} must be finite")
        shape = tuple(shape)
        if self.k.ndim == 0:
            out_shape = shape
        elif self.k.ndim == 2 and shape == (self.k.shape[1],):
            out_shape = (self.k.shape[0],)
        else:
            raise WiringError(f"gain {name!r}: K of shape {self.k.shape} cannot act on a port of shape {shape}")
        super().__init__(
            name,
            inputs=[Port("u", shape, in_unit)],
            outputs=[Port("y", out_shape, out_unit or in_unit)],
            dt=dt,
            feedthrough=True,
        )

    def kernel(self):
        from magctl.core import kernels as k

        if self.k.ndim == 0:
            return Kernel(step=k.gain_scalar_step, params=(float(self.k),))
        return Kernel(step=k.gain_matrix_step, params=(np.ascontiguousarray(self.k),))

    def to_control(self):
        n = _size(self.inputs["u"].shape)
        D = self.k * np.eye(n) if self.k.ndim == 0 else self.k
        return _ss(np.zeros((0, 0)), np.zeros((0, n)), np.zeros((D.shape[0], 0)), D, dt=self.dt)


class Sum(Block):
    """``y[k] = Σ sᵢ uᵢ[k]`` with signs given as a string such as ``"+-"``.

    Inputs are named ``u0, u1, …``.
    """

    def __init__(self, name: str, signs: str = "++", *, shape=(), unit: str = DIMENSIONLESS,
                 dt: float = FRAME_PERIOD_S):
        if not signs or set(signs) - {"+", "-"}:
            raise WiringError(f"sum {name!r}: signs {signs!r} must be a string of '+' and '-'")
        self.signs = [1.0 if s == "+" else -1.0 for s in signs]
        ins = [Port(f"u{i}", tuple(shape), unit) for i in range(len(signs))]
        super().__init__(name, inputs=ins, outputs=[Port("y", tuple(shape), unit)], dt=dt, feedthrough=True)
        self._names = [p.name for p in ins]

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(step=k.sum_step, params=(np.asarray(self.signs, dtype=float),))

    def to_control(self):
        n = _size(self.outputs["y"].shape)
        D = np.hstack([s * np.eye(n) for s in self.signs])
        return _ss(np.zeros((0, 0)), np.zeros((0, D.shape[1])), np.zeros((n, 0)), D, dt=self.dt)


class Delay(Block):
    """Pure delay ``y[k] = u[k - d]`` (transfer function z⁻ᵈ), ``initial`` before the first input.

    The state is the past inputs ``u{j} = u[k−j]``, ``j = d … 1`` (oldest first, the state vector
    of :meth:`to_control` as well); a step passes the arrays along without copying them.
    """

    def __init__(self, name: str, d: int, *, shape=(), unit: str = DIMENSIONLESS, dt: float = FRAME_PERIOD_S,
                 initial=0.0):
        if int(d) != d or d < 1:
            raise WiringError(f"delay {name!r}: d={d!r} must be a positive integer (use a wire for d=0)")
        self.d = int(d)
        self.initial = initial
        super().__init__(name, inputs=[Port("u", tuple(shape), unit)], outputs=[Port("y", tuple(shape), unit)],
                         dt=dt, feedthrough=False)
        self._names = [f"u{j}" for j in range(self.d, 0, -1)]  # oldest first

    def state_vars(self):
        shape = self.inputs["u"].shape
        return tuple(StateVar(n, shape, symbol=f"u[k−{n[1:]}]", description=f"input {n[1:]} steps ago")
                     for n in self._names)

    def initial_state(self, batch, rng=None):
        return {n: as_batch(self.initial, self.inputs["u"], batch) for n in self._names}

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(output=k.delay_output, update=k.delay_update)

    def to_control(self):
        n = _size(self.inputs["u"].shape)
        d = self.d
        # state x = [u[k-d], …, u[k-1]] stacked per channel block
        A = np.zeros((d * n, d * n))
        A[: (d - 1) * n, n:] = np.eye((d - 1) * n)
        B = np.zeros((d * n, n))
        B[(d - 1) * n:, :] = np.eye(n)
        C = np.zeros((n, d * n))
        C[:, :n] = np.eye(n)
        labels = [lbl for name in self._names for lbl in _labels(name, self.inputs["u"].shape)]
        return _ss(A, B, C, np.zeros((n, n)), dt=self.dt, states=labels)


class Integrator(Block):
    """Forward-Euler discrete integrator ``x[k+1] = x[k] + g·T·u[k]``, ``y[k] = x[k]``.

    Transfer function ``g·T / (z − 1)``. The output unit is the input unit times seconds
    unless given.
    """

    def __init__(self, name: str, *, gain: float = 1.0, shape=(), in_unit: str = DIMENSIONLESS,
                 out_unit: str | None = None, dt: float = FRAME_PERIOD_S, initial=0.0):
        self.gain = float(gain)
        self.initial = initial
        super().__init__(name, inputs=[Port("u", tuple(shape), in_unit)],
                         outputs=[Port("y", tuple(shape), out_unit or f"({in_unit})*s")], dt=dt,
                         feedthrough=False)

    def state_vars(self):
        return (StateVar("x", self.outputs["y"].shape, symbol="x", description="the integral"),)

    def initial_state(self, batch, rng=None):
        return {"x": as_batch(self.initial, self.outputs["y"], batch)}

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(output=k.delay_output, update=k.integrator_update, params=(self.gain * self.dt,))

    def to_control(self):
        n = _size(self.inputs["u"].shape)
        eye = np.eye(n)
        return _ss(eye, self.gain * self.dt * eye, eye, np.zeros((n, n)), dt=self.dt,
                          states=_labels("x", self.outputs["y"].shape))


class PI(Block):
    """Discrete PI controller with conditional-integration anti-windup and output saturation.

    ``u[k] = Kp·e[k] + Ki·I[k]``; ``I[k+1] = I[k] + T·e[k]`` except while the
    unsaturated ``u[k]`` exceeds the limit, when ``I`` is held. With ``norm=True``
    the limit applies to the vector norm ``‖u‖`` (direction kept), otherwise
    element-wise. The linear model (``to_control``) is the unsaturated law,
    ``C(z) = Kp + Ki·T/(z − 1)`` (a static gain ``Kp`` when ``Ki = 0``).

    Ports: input ``e`` (error), outputs ``u`` (command) and ``saturated`` (bool).
    """

    def __init__(self, name: str, kp: float, ki: float, *, shape=(), limit: float | None = None,
                 norm: bool = True, saturate: bool = True, in_unit: str = DIMENSIONLESS,
                 out_unit: str = DIMENSIONLESS, dt: float = FRAME_PERIOD_S):
        self.kp, self.ki = check_finite(f"PI {name!r}: kp", kp), check_finite(f"PI {name!r}: ki", ki)
        self.limit = None if limit is None else check_positive(f"PI {name!r}: limit", limit)
        self.norm = bool(norm) and len(tuple(shape)) > 0
        self.saturate = bool(saturate)
        super().__init__(
            name,
            inputs=[Port("e", tuple(shape), in_unit)],
            outputs=[Port("u", tuple(shape), out_unit), Port("saturated", (), DIMENSIONLESS, "bool")],
            dt=dt,
            feedthrough=True,
        )

    def state_vars(self):
        return (StateVar("I", self.inputs["e"].shape, symbol="I", description="integral of the error"),)

    def initial_state(self, batch, rng=None):
        return {"I": self.inputs["e"].empty(batch)}

    def kernel(self):
        from magctl.core import kernels as k

        mode = 0 if self.limit is None else 1 if self.norm else 2
        limit = 0.0 if self.limit is None else self.limit
        return Kernel(step=k.pi_step, params=(self.kp, self.ki, self.dt, limit, mode, self.saturate))

    def to_control(self):
        n = _size(self.inputs["e"].shape)
        eye = np.eye(n)
        if self.ki == 0.0:
            return _ss(np.zeros((0, 0)), np.zeros((0, n)), np.zeros((n, 0)), self.kp * eye, dt=self.dt)
        return _ss(eye, self.dt * eye, self.ki * eye, self.kp * eye, dt=self.dt,
                          states=_labels("I", self.inputs["e"].shape))


class StateSpace(Block):
    """Discrete state space ``x[k+1] = A x + B u``, ``y = C x + D u`` on vector ports ``u``, ``y``."""

    def __init__(self, name: str, A, B, C, D, *, in_unit: str = DIMENSIONLESS, out_unit: str = DIMENSIONLESS,
                 dt: float = FRAME_PERIOD_S, x0: Sequence[float] | None = None):
        self.A, self.B, self.C, self.D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (A, B, C, D))
        n, m, p = self.A.shape[0], self.B.shape[1], self.C.shape[0]
        if self.A.shape != (n, n) or self.B.shape != (n, m) or self.C.shape != (p, n) or self.D.shape != (p, m):
            raise WiringError(
                f"state space {name!r}: inconsistent shapes A{self.A.shape} B{self.B.shape} "
                f"C{self.C.shape} D{self.D.shape}"
            )
        self.x0 = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float)
        super().__init__(name, inputs=[Port("u", (m,), in_unit)], outputs=[Port("y", (p,), out_unit)], dt=dt,
                         feedthrough=bool(np.any(self.D)))

    @classmethod
    def from_control(cls, name: str, sys, **kw) -> StateSpace:
        """Wrap a discrete python-control system (its ``dt`` becomes the block's period)."""
        ss = _ss(sys)
        if not ss.isdtime(strict=True):
            raise WiringError(f"state space {name!r}: the system must be discrete-time with a numeric dt")
        return cls(name, ss.A, ss.B, ss.C, ss.D, dt=float(ss.dt), **kw)

    def state_vars(self):
        return (StateVar("x", (self.A.shape[0],), symbol="x", description="state vector"),)

    def initial_state(self, batch, rng=None):
        return {"x": np.broadcast_to(self.x0, (batch, self.x0.size)).copy()}

    def kernel(self):
        from magctl.core import kernels as k

        params = tuple(np.ascontiguousarray(m) for m in (self.A, self.B, self.C, self.D))
        if self.feedthrough:  # x' = A x reads every x after the first x' is written: no in-place update
            return Kernel(step=k.state_space_step, params=params, in_place=False)
        return Kernel(output=k.state_space_output, update=k.state_space_update, params=params, in_place=False)

    def to_control(self):
        return _ss(self.A, self.B, self.C, self.D, dt=self.dt, states=_labels("x", (self.A.shape[0],)))
