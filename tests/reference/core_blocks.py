"""Numpy references of the core blocks (linear blocks, norm saturation, Gaussian noise)."""

from __future__ import annotations

import numpy as np

from magctl.core.linear import PI, Constant, Delay, Gain, Integrator, StateSpace, Sum
from magctl.core.nonlinear import GaussianNoise, NormSaturation


def rows_times(x, m):
    """``x @ m`` per trial, summed in the order of ``x``'s elements."""
    return np.einsum("bi,ij->bj", x, m)


def vector_norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm of each trial's vector: ``(B, n)`` → ``(B,)`` (``hypot`` for the common 2-D case)."""
    if v.shape[1] == 2:
        return np.hypot(v[:, 0], v[:, 1])
    return np.sqrt(np.einsum("bi,bi->b", v, v))


def clip_norm(v: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Each trial's vector scaled to ``‖v‖ ≤ limit``, direction kept; and the flags of those clipped."""
    mag = vector_norm(v)
    over = mag > limit
    scale = np.where(over, limit / np.where(over, mag, 1.0), 1.0)
    return np.where(over[:, None], v * scale[:, None], v), over


class NumpyForm:
    """First base of every reference: no kernel, so the block runs the numpy methods written here."""

    def kernel(self):
        return None


class SteppedForm(NumpyForm):
    """A reference written as one ``step``: its outputs and next state come from it."""

    def output(self, state, u):
        return self.step(state, u)[0]

    def update(self, state, u):
        return self.step(state, u)[1]


class RefConstant(NumpyForm, Constant):
    def output(self, state, u):
        return {"y": state["y"]}


class RefGain(NumpyForm, Gain):
    def output(self, state, u):
        x = u["u"]
        return {"y": x * self.k if self.k.ndim == 0 else rows_times(x, self.k.T)}


class RefSum(NumpyForm, Sum):
    def output(self, state, u):
        names = list(self.inputs)
        y = u[names[0]] * self.signs[0]
        for name, s in zip(names[1:], self.signs[1:], strict=True):
            y = y + u[name] if s > 0 else y - u[name]
        return {"y": y}


class RefDelay(NumpyForm, Delay):
    def output(self, state, u):
        return {"y": state[self._names[0]]}

    def update(self, state, u):
        names = self._names
        new = {names[j]: state[names[j + 1]] for j in range(self.d - 1)}
        new[names[-1]] = u["u"]
        return new


class RefIntegrator(NumpyForm, Integrator):
    def output(self, state, u):
        return {"y": state["x"]}

    def update(self, state, u):
        return {"x": state["x"] + (self.gain * self.dt) * u["u"]}


class RefPI(SteppedForm, PI):
    """``u = Kp e + Ki I``, saturated by norm or element; ``I`` held while the unsaturated ``u`` is over."""

    def _excess(self, u):
        if self.norm:
            return vector_norm(u) if u.ndim == 2 else np.sqrt((u * u).reshape(u.shape[0], -1).sum(axis=1))
        return np.abs(u).reshape(u.shape[0], -1).max(axis=1) if u.ndim > 1 else np.abs(u)

    def step(self, state, u):
        e = u["e"]
        raw = self.kp * e + self.ki * state["I"]
        if self.limit is None:
            return {"u": raw, "saturated": np.zeros(raw.shape[0], dtype=bool)}, {"I": state["I"] + self.dt * e}
        mag = self._excess(raw)
        sat = mag > self.limit
        hold = (~sat).reshape((-1,) + (1,) * (e.ndim - 1))
        nxt = {"I": state["I"] + (self.dt * e) * hold}
        if self.saturate:
            if self.norm:
                scale = np.where(sat, self.limit / np.where(sat, mag, 1.0), 1.0)
                raw = raw * scale.reshape((-1,) + (1,) * (raw.ndim - 1))
            else:
                raw = np.clip(raw, -self.limit, self.limit)
        return {"u": raw, "saturated": sat}, nxt



class RefStateSpace(NumpyForm, StateSpace):
    def output(self, state, u):
        y = rows_times(state["x"], self.C.T)
        if self.feedthrough:
            y = y + rows_times(u["u"], self.D.T)
        return {"y": y}

    def update(self, state, u):
        return {"x": rows_times(state["x"], self.A.T) + rows_times(u["u"], self.B.T)}


class RefNormSaturation(NumpyForm, NormSaturation):
    def output(self, state, u):
        y, sat = clip_norm(u["u"], self.limit)
        return {"y": y, "saturated": sat}


class RefGaussianNoise(NumpyForm, GaussianNoise):
    def output(self, state, u):
        rng = state["rng"]
        if rng is None:
            return {"y": u["u"]}
        return {"y": u["u"] + self.sigma * rng.standard_normal(self.inputs["u"].shape, at=state["k"])}

    def update(self, state, u):
        return {"rng": state["rng"], "k": state["k"] + 1}


REFERENCES = {Constant: RefConstant, Gain: RefGain, Sum: RefSum, Delay: RefDelay, Integrator: RefIntegrator,
                   PI: RefPI, StateSpace: RefStateSpace, NormSaturation: RefNormSaturation,
                   GaussianNoise: RefGaussianNoise}
