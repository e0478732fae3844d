"""Small generic nonlinear blocks: norm saturation and additive Gaussian noise."""

from __future__ import annotations

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.block import Block, StateVar, rng_var
from magctl.core.kernel import Kernel
from magctl.core.ports import DIMENSIONLESS, Port


def vector_norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm of each trial's vector: ``(B, n)`` → ``(B,)`` (``hypot`` for the common 2-D case)."""
    if v.shape[1] == 2:
        return np.hypot(v[:, 0], v[:, 1])
    return np.sqrt(np.einsum("bi,bi->b", v, v))


def clip_norm(v: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale each trial's vector ``v[b]`` so that ``‖v[b]‖ ≤ limit``, keeping its direction.

    Returns the clipped array and a boolean ``(B,)`` flag of the trials that were clipped.
    """
    mag = vector_norm(v)
    over = mag > limit
    if not over.any():
        return v, over
    scale = np.where(over, limit / np.where(over, mag, 1.0), 1.0)
    return v * scale[:, None], over


class NormSaturation(Block):
    """``y = u · min(1, L/‖u‖)``: a vector limit that keeps direction; reports ``saturated``."""

    def __init__(self, name: str, limit: float, *, shape=(2,), unit: str = DIMENSIONLESS,
                 dt: float = FRAME_PERIOD_S):
        self.limit = float(limit)
        super().__init__(name, inputs=[Port("u", tuple(shape), unit)],
                         outputs=[Port("y", tuple(shape), unit), Port("saturated", (), DIMENSIONLESS, "bool")],
                         dt=dt, feedthrough=True)

    def output(self, state, u):
        y, sat = clip_norm(u["u"], self.limit)
        return {"y": y, "saturated": sat}

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

    def output(self, state, u):
        rng = state["rng"]
        if rng is None:  # noise off (a linearisation's operating path)
            return {"y": u["u"]}
        # step k's draws, by position: output() is a function of the state
        return {"y": u["u"] + self.sigma * rng.standard_normal(self.inputs["u"].shape, at=state["k"])}

    def update(self, state, u):
        return {"rng": state["rng"], "k": state["k"] + 1}

    def kernel(self):
        from magctl.core import kernels as k

        return Kernel(step=k.gaussian_noise_step, params=(self.sigma,), stream="rng")
