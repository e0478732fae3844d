"""Iterative learning laws of the push tasks, stepped once per push attempt.

Both laws are the discrete integrator ``x(i+1) = x(i) + g·e(i)``, ``y(i) = x(i)``
with the attempt index ``i`` as time (``dt = 1`` attempt):

* front pushing, eq 13: ``δ(i+1) = δ(i) + K_c [P_g(i) − P_s(i)]``, with ``e`` the
  goal-minus-sphere distance along the pushing line and ``g = K_c``;
* side pushing, eq 18: ``Δ(i+1) = Δ(i) ± K_s [D_s,act(i) − D_s,des(i)]``, with ``e``
  the bracket of eq 18 exactly as printed. The printed ``+`` makes the loop
  diverge (``F`` decreases with the displacement, so an over-push would ask for
  a smaller gap and push harder); the law therefore uses ``g = −K_s`` unless
  ``printed_sign=True``. ``docs/push-control.md`` gives the evidence.

Each law is written once, as its kernel (:mod:`magctl.control.kernels`): the 30 Hz push tasks' kernels run it
on the trials that just finished an attempt, the attempt maps of :mod:`magctl.stability.iteration` through
:meth:`AttemptLaw.update_where`, and the iteration-domain diagrams take :meth:`LearningLaw.to_control`
(``g/(z − 1)``, eq 14 and 19).
"""

from __future__ import annotations

import control
import numpy as np

from magctl.core.block import Block, StateVar, as_batch
from magctl.core.errors import MagctlError
from magctl.core.ports import Port

ATTEMPT = 1.0
"""Sample period of the iteration domain: one push attempt."""


class AttemptLaw:
    """Mix-in of the law blocks stepped once per push attempt (their behaviour is their kernel)."""

    def update_where(self, state, u, mask) -> dict:
        """The next state of the trials in ``mask`` (those that just finished an attempt), the others' kept: the
        law's update (its kernel, through :meth:`~magctl.core.block.Block.update`) taken per trial."""
        mask = np.asarray(mask, dtype=bool)
        nxt = self.update(state, u)
        return {k: np.where(mask.reshape((-1,) + (1,) * (np.ndim(v) - 1)), v, state[k]) for k, v in nxt.items()}


class LearningLaw(AttemptLaw, Block):
    """Forward-Euler integrator over push attempts, ``x(i+1) = x(i) + g·e(i)`` (eq 13, eq 18).

    Parameters
    ----------
    name : str
        Block name.
    gain : float or (B,) array_like
        Integration gain ``g`` (``K_c`` for eq 13, ``−K_s`` for eq 18 as corrected); one
        value per trial runs a gain sweep in one batch (no transfer function then).
    initial : float or array_like
        ``x(0)`` in metres: a scalar for every trial or one value per trial
        (``δ(0)`` of eq 10 as a feed-forward term, ``Δ(0) = 0`` for eq 17).
    unit : str
        Unit of ``e`` and ``x`` (metres on the rig and in the tasks).

    Ports
    -----
    input ``e`` () — the learning error of the attempt just finished;
    output ``y`` () — the correction to apply in the next attempt (``δ`` or ``Δ``).
    """

    def __init__(self, name: str, gain: float, *, initial=0.0, unit: str = "m", dt: float = ATTEMPT):
        gain = np.asarray(gain, dtype=float)
        if gain.ndim > 1 or not np.all(np.isfinite(gain)):
            raise MagctlError(f"learning law {name!r}: gain {gain!r} must be a finite scalar or one value per trial")
        init = np.asarray(initial, dtype=float)
        if not np.all(np.isfinite(init)):
            raise MagctlError(f"learning law {name!r}: initial value {initial!r} must be finite")
        self.gain = float(gain) if gain.ndim == 0 else gain
        self.initial = init
        super().__init__(name, inputs=[Port("e", (), unit)], outputs=[Port("y", (), unit)], dt=dt,
                         feedthrough=False)

    def state_vars(self):
        return (StateVar("x", (), symbol="x", description="the correction δ or Δ, m"),)

    def initial_state(self, batch, rng=None):
        for what, arr in (("initial values", self.initial), ("gains", np.asarray(self.gain))):
            if arr.ndim == 1 and arr.shape[0] != batch:
                raise MagctlError(f"learning law {self.name!r}: {arr.shape[0]} per-trial {what} for a batch of {batch}")
        return {"x": as_batch(self.initial, self.outputs["y"], batch)}

    def kernel(self):
        """The integrator ``y(i) = x(i)``, ``x(i+1) = x(i) + g·e(i)`` (:func:`magctl.control.kernels.law_output`,
        ``law_update``)."""
        from magctl.control import kernels as k
        from magctl.core.kernel import Kernel

        return Kernel(output=k.law_output, update=k.law_update,
                      params=(np.atleast_1d(np.asarray(self.gain, dtype=float)).copy(),))

    def to_control(self):
        """``g / (z − 1)`` as a python-control state space with ``dt`` = 1 attempt."""
        if np.ndim(self.gain):
            raise MagctlError(f"learning law {self.name!r} has per-trial gains: no single transfer function")
        return control.ss([[1.0]], [[self.gain]], [[1.0]], [[0.0]], dt=self.dt)


def front_push_law(kc: float, delta0=0.0, name: str = "front_law") -> LearningLaw:
    """Eq 13: ``δ(i+1) = δ(i) + K_c [P_g − P_s]``; ``e`` is ``P_g − P_s`` along the pushing line.

    Parameters
    ----------
    kc : float
        ``K_c``; the loop is stable for ``0 < K_c < 2`` (eq 15).
    delta0 : float or array_like
        ``δ(0)`` in metres (the model's release displacement ``D_p,r``, or 0).
    """
    return LearningLaw(name, _finite_gain("K_c", kc), initial=delta0)


def side_push_law(ks: float, *, printed_sign: bool = False, name: str = "side_law") -> LearningLaw:
    """Eq 18 with ``e = D_s,act − D_s,des`` (the printed bracket); ``Δ(0) = 0``.

    Parameters
    ----------
    ks : float
        ``K_s``.
    printed_sign : bool
        False (default): ``Δ(i+1) = Δ(i) − K_s e``, the sign under which eq 19–20 hold.
        True: ``+K_s e`` exactly as printed, which diverges for every ``K_s > 0``.
    """
    ks = _finite_gain("K_s", ks)
    return LearningLaw(name, ks if printed_sign else -ks, initial=0.0)


def _finite_gain(symbol: str, value):
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise MagctlError(f"gain {symbol}={value!r} is not a number") from None
    if v.ndim > 1 or not np.all(np.isfinite(v)):
        raise MagctlError(f"gain {symbol}={value!r} must be finite (a number, or one per trial)")
    return float(v) if v.ndim == 0 else v
