"""Small generic nonlinear blocks: norm saturation and additive Gaussian noise (their behaviour: their kernels in
:mod:`magctl.core.kernels`)."""

from __future__ import annotations

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port


class NormSaturation(Block):
    """``y = u · min(1, L/‖u‖)``: a vector limit that keeps direction; reports ``saturated``."""

    def __init__(self, name: str, limit: float, *, shape=(2,), unit: str = DIMENSIONLESS,
                 dt: float = FRAME_PERIOD_S):
        self.limit = float(limit)
        super().__init__(name, inputs=[Port("u", tuple(shape), unit)],
                         outputs=[Port("y", tuple(shape), unit), Port("saturated", (), DIMENSIONLESS, "bool")],
                         dt=dt, feedthrough=True)

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(step=k.norm_saturation_step, params=(self.limit,))


class GaussianNoise(Block):
    """``y[k] = u[k] + σ·n[k]`` with ``n`` drawn from the trial's own stream, N(0, 1) per element.

    ``n[k]`` is the stream's draw at position ``k`` (the state's step count), so the
    block is a function of its state; with no stream (``rng=None``) it passes ``u``.
    """

    def __init__(self, name: str, sigma: float, *, shape=(), unit: str = DIMENSIONLESS,
                 dt: float = FRAME_PERIOD_S):
        self.sigma = float(sigma)
        super().__init__(name, inputs=[Port("u", tuple(shape), unit)], outputs=[Port("y", tuple(shape), unit)],
                         dt=dt, feedthrough=True)

    @property
    def uses_random(self) -> bool:
        return True

    def state_vars(self):
        return (rng_var(), StateVar("k", (), "int64", "k", "steps drawn so far", batched=False))

    def initial_state(self, batch, rng=None):
        return {"rng": rng, "k": 0}

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(step=k.gaussian_noise_step, params=(self.sigma,), stream="rng")
