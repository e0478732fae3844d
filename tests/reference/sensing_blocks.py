"""Numpy references of the sensing blocks: the camera (positions mode), the blackout gate, the tracker (raw and
Kalman modes).

The camera's images mode and the tracker's particle mode have no kernel: the library runs them in Python, and
the references below hand those modes to it.
"""

from __future__ import annotations

import numpy as np

from magctl.sensing.blackout import Blackout
from magctl.sensing.camera import Camera
from magctl.sensing.tracker import START_VELOCITY_VAR, Tracker
from reference.core_blocks import NumpyForm, SteppedForm


def quantise(x: np.ndarray, pixel: float) -> np.ndarray:
    """Round coordinates (m) to the nearest pixel centre: ``s·round(x/s)`` (round half to even)."""
    return pixel * np.round(x / pixel)


class RefCamera(NumpyForm, Camera):
    """Positions mode: a frame sampled at step ``k`` is measured and delivered at step ``k + L``.

    With ``n ~ N(0, 1)`` and ``w ~ U[0, 1)`` drawn from the trial's stream at the delivering step's position,
    pixel size ``s``::

        valid = full ∧ (w ≥ p_drop) ∧ p ∈ [0, (W−1)s] × [0, (H−1)s]
        p̃ = s·round((p + s σ_px n) / s)          (robot and each sphere centre)
        ψ̃ = arg exp(i (ψ + σ_θ n))               (heading, wrapped to (−π, π])

    and ``p̃, ψ̃`` hold the last delivered values when not ``valid``. Without latency the frame of step ``k``
    is measured at position ``k``; with latency ``L`` the pipeline of the last ``L`` frames is in the state,
    and ``update`` measures the frame delivered next at position ``k + 1`` (the state holds the measurement
    delivered now).
    """

    def _sample(self, state, u):
        """The true plant state of the frame delivered now, and whether one exists."""
        if self.latency == 0:
            return u["position"], u["heading"], u["spheres"], np.ones(u["position"].shape[0], dtype=bool)
        L = self.latency
        return state[f"pos{L}"], state[f"head{L}"], state[f"sph{L}"], state[f"full{L}"]

    def _draws(self, state, batch, k):
        """Step ``k``'s draws: standard normals ``(B, 3 + 2N)`` and one uniform ``(B, 1)``; none without a
        stream (no noise, no drop)."""
        rng = state["rng"]
        if rng is None:
            return np.zeros((batch, 3 + 2 * self.n_spheres)), np.ones((batch, 1))
        return rng.standard_normal((3 + 2 * self.n_spheres,), at=k), rng.random((1,), at=k)

    def _measure(self, state, sample, k) -> dict:
        """The measurement of step ``k`` from ``sample``, holding ``state``'s last one where not valid."""
        pos, head, sph, full = sample
        b, n, s = pos.shape[0], self.n_spheres, self.pixel
        normal, uniform = self._draws(state, b, k)
        fov_w, fov_h = self.field_of_view
        in_view = (pos[:, 0] >= 0) & (pos[:, 0] <= fov_w) & (pos[:, 1] >= 0) & (pos[:, 1] <= fov_h)
        valid = full & (uniform[:, 0] >= self.p_drop) & in_view
        robot = quantise(pos + s * self.sigma_px * normal[:, :2], s)
        heading = np.angle(np.exp(1j * (head + self.sigma_heading * normal[:, 2])))
        spheres = quantise(sph + s * self.sigma_px * normal[:, 3:].reshape(b, n, 2), s)
        return {"meas_pos": np.where(valid[:, None], robot, state["meas_pos"]),
                "meas_head": np.where(valid, heading, state["meas_head"]),
                "meas_sph": np.where(valid[:, None, None], spheres, state["meas_sph"]), "valid": valid}

    @staticmethod
    def _positions_out(m: dict) -> dict:
        return {"robot_meas": m["meas_pos"], "heading_meas": m["meas_head"], "spheres_meas": m["meas_sph"],
                "valid": m["valid"]}

    def step(self, state, u):
        if self.mode != "positions":
            return super().step(state, u)
        if self.latency:
            return self.output(state, u), self.update(state, u)
        m = self._measure(state, self._sample(state, u), state["k"])
        return self._positions_out(m), {"rng": state["rng"], "k": state["k"] + 1, "meas_pos": m["meas_pos"],
                                        "meas_head": m["meas_head"], "meas_sph": m["meas_sph"]}

    def output(self, state, u):
        if self.mode != "positions":
            return super().output(state, u)
        if self.latency:
            return self._positions_out(state)
        return self.step(state, u)[0]

    def update(self, state, u):
        if self.mode != "positions":
            return super().update(state, u)
        if not self.latency:
            return self.step(state, u)[1]
        # the pipeline moves on by one frame (arrays passed along, never written), then the frame now
        # oldest is measured at the next stream position
        new = {"rng": state["rng"], "k": state["k"] + 1}
        for j in range(self.latency, 1, -1):
            for x in ("pos", "head", "sph", "full"):
                new[f"{x}{j}"] = state[f"{x}{j - 1}"]
        new |= {"pos1": u["position"], "head1": u["heading"], "sph1": u["spheres"],
                "full1": np.ones(u["heading"].shape[0], dtype=bool)}
        new |= {"meas_pos": state["meas_pos"], "meas_head": state["meas_head"], "meas_sph": state["meas_sph"]}
        return new | self._measure(new, self._sample(new, None), new["k"])


class RefBlackout(NumpyForm, Blackout):
    """``valid_out = valid ∧ ¬(t0 ≤ k·T < t1)``."""

    def output(self, state, u):
        w = self.window
        if w is not None and w[0] <= state["k"] * self.dt < w[1]:
            return {"valid_out": np.zeros_like(u["valid"])}
        return {"valid_out": u["valid"]}

    def update(self, state, u):
        return {"k": state["k"] + 1}


class RefTracker(SteppedForm, Tracker):
    """Raw and Kalman modes, the B trials, objects and axes in lockstep.

    Kalman mode, per object and axis, state ``x = [p, v]``, ``H = [1, 0]`` (filterpy's notation)::

        predict   x⁻ = F x,             P⁻ = F P Fᵀ + Q
        update    S = P⁻₀₀ + R,         K = P⁻[:, 0] / S
                  x = x⁻ + K (z − x⁻₀), P = P⁻ − K P⁻[0, :]

    updated when the frame is valid and the track started; started at ``x = [z, 0]``,
    ``P = diag(R, v₀²)`` on the first valid frame; predicted only on an invalid frame. Raw mode: ``p = z``
    and ``v = (z − p_prev)/T`` on a valid frame of a started track (``v = 0`` otherwise). Estimates
    ``p + d·T·v`` (Kalman mode, ``d = predict_frames``). ``lost`` after ``max_coast`` frames without a valid
    frame or before the first: velocity 0, positions held (``hold``) or NaN with the heading (``nan``).
    """

    def _posterior(self, state, u):
        """``(x, P, init)`` after this frame's measurement (fresh arrays; ``state`` is not modified)."""
        valid = np.asarray(u["valid"], dtype=bool)
        z = np.concatenate([u["robot_meas"][:, None, :], u["spheres_meas"]], axis=1)  # (B, M, 2)
        x, P, init = state["x"], state["P"], state["init"]
        if self.mode == "raw":
            xn = x.copy()
            xn[..., 1] = np.where((valid & init)[:, None, None], (z - x[..., 0]) / self.dt, 0.0)
            xn[..., 0] = np.where(valid[:, None, None], z, x[..., 0])
            return xn, P, init | valid
        xp = np.einsum("ij,bmaj->bmai", self.F, x)                  # F x
        Pp = self.F @ P @ self.F.T + self.Q                         # F P Fᵀ + Q
        S = Pp[..., 0, 0] + self.R                                  # (B, M)
        K = Pp[..., :, 0] / S[..., None]                            # (B, M, 2)
        innov = z - xp[..., 0]                                      # (B, M, 2 axes)
        xu = xp + K[:, :, None, :] * innov[..., None]
        Pu = Pp - K[..., :, None] * Pp[..., 0, :][..., None, :]
        upd = (valid & init)[:, None, None, None]
        start = (valid & ~init)[:, None, None, None]
        x0 = np.zeros_like(x)
        x0[..., 0] = z
        P0 = np.zeros_like(P)
        P0[..., 0, 0] = self.R
        P0[..., 1, 1] = START_VELOCITY_VAR
        tracked = init[:, None, None, None]
        xn = np.where(start, x0, np.where(tracked, np.where(upd, xu, xp), x))
        Pn = np.where(start, P0, np.where(tracked, np.where(upd, Pu, Pp), P))
        return xn, Pn, init | valid

    def step(self, state, u):
        if self.mode == "particle":
            return super().step(state, u)
        valid = np.asarray(u["valid"], dtype=bool)
        missed = np.where(valid, 0, state["missed"] + 1)
        x, P, init = self._posterior(state, u)
        heading = np.where(valid, u["heading_meas"], state["heading"])
        lost = ~init | (missed > self.max_coast)
        ahead = self.predict_frames * self.dt if self.mode == "kalman" else 0.0
        p = x[..., 0] + ahead * x[..., 1]
        pos, vel, sph = p[:, 0], np.where(lost[:, None], 0.0, x[:, 0, :, 1]), p[:, 1:]
        new = dict(state) | {"x": x, "P": P, "init": init, "heading": heading, "missed": missed}
        if self.on_loss == "hold":
            pos = np.where(lost[:, None], state["held_pos"], pos)
            sph = np.where(lost[:, None, None], state["held_sph"], sph)
            new |= {"held_pos": pos, "held_sph": sph}
        else:
            pos = np.where(lost[:, None], np.nan, pos)
            vel = np.where(lost[:, None], np.nan, vel)
            sph = np.where(lost[:, None, None], np.nan, sph)
            heading = np.where(lost, np.nan, heading)
        return {"robot_est": pos, "heading_est": heading, "velocity_est": vel, "spheres_est": sph, "lost": lost}, new



REFERENCES = {Camera: RefCamera, Blackout: RefBlackout, Tracker: RefTracker}
