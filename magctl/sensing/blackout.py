"""A gate between camera and tracker that drops every frame in a time window: forced tracking loss (its behaviour:
its kernel, :func:`magctl.sensing.kernels.blackout_step`)."""

from __future__ import annotations

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port


class Blackout(Block):
    """Camera frames dropped during a time window ``[t0, t1)``: ``valid_out = valid ∧ ¬blackout``.

    Sits between the camera and the tracker so that a blackout is a real loss of detections
    (the tracker coasts, then reports ``lost``), for tests of the controller's loss handling.

    Parameters
    ----------
    window : (float, float) or None
        ``[t0, t1)`` in s of plant time; None passes every frame.
    """

    def __init__(self, name: str = "blackout", window=None, dt: float = FRAME_PERIOD_S):
        self.window = None if window is None else (float(window[0]), float(window[1]))
        super().__init__(name, inputs=[Port("valid", (), DIMENSIONLESS, "bool")],
                         outputs=[Port("valid_out", (), DIMENSIONLESS, "bool")], dt=dt, feedthrough=True)

    def state_vars(self):
        return (StateVar("k", (), "int64", "k", "frames stepped (the clock of the window)", batched=False),)

    def initial_state(self, batch, rng=None):
        return {"k": 0}

    def kernel(self):
        from magctl.sensing import kernels as k

        t0, t1 = self.window if self.window is not None else (0.0, 0.0)
        return Kernel(step=k.blackout_step, params=(self.window is not None, t0, t1, self.dt))
