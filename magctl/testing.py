"""Reference loops used by tests and benchmarks.

* Benchmark B1, the visual-servo reference loop, in three implementations
  (magctl diagram, hand-vectorised numpy, python-control);
* small importable trial functions for :func:`magctl.sweep.run_trials`
  (functions handed to a process pool or a Dask worker are pickled by reference,
  so they must live in an importable module, not in a test file or ``__main__``).

B1 definition (units µm and s here, as in the benchmark's statement): T = 1/30 s,
1 800 steps, 2-D. Plant ``p[k+1] = p[k] + T·clip(u[k])`` with the vector norm
of ``u`` limited to 400 µm/s (direction kept). Camera ``y[k] = p[k−2] + n[k]``,
``n ~ N(0, (3 µm)²)`` per axis, drawn from the trial's counter-based stream. Discrete PI on
``e = r − y``: ``u = Kp·e[k] + Ki·I[k]``, ``I[k+1] = I[k] + T·e[k]`` except while
``‖u‖ > 400`` (anti-windup: hold I); Kp = 1.5 s⁻¹, Ki = 0.3 s⁻²; r = (1000, 500) µm,
``p[0] = 0``.

The noise of trial ``k`` is the noise block's stream in a magctl simulation seeded with ``seed``
(``TrialStreams.for_block(seed, [k], "camera_noise")`` read at steps 0 … 1799), so all three
implementations see the same noise.
"""

from __future__ import annotations

from collections.abc import Sequence

import control
import numpy as np

from magctl.core import PI, Constant, Delay, Diagram, GaussianNoise, Integrator, NormSaturation, Sum, simulate
from magctl.core.random import TrialStreams

T = 1.0 / 30.0
STEPS = 1800
SPEED_LIMIT = 400.0  # µm/s
NOISE_SIGMA = 3.0  # µm
KP, KI = 1.5, 0.3
REFERENCE = (1000.0, 500.0)  # µm
DELAY = 2


def b1_diagram(noise: str = "drawn") -> Diagram:
    """B1 as a magctl diagram (ports in µm to match the benchmark's statement).

    ``noise="drawn"``: the camera noise comes from the noise block's own per-trial stream.
    ``noise="input"``: the noise is a diagram input ``n`` (µm, ``(B, T, 2)``), fed as every block-diagram
    peer gets it (:func:`b1_noise` gives the drawn one's numbers).
    """
    if noise not in ("drawn", "input"):
        raise ValueError(f"b1_diagram: noise={noise!r} must be 'drawn' or 'input'")
    blocks = [
        Constant("ref", REFERENCE, shape=(2,), unit="um"),
        Sum("err", "+-", shape=(2,), unit="um"),
        PI("pi", KP, KI, shape=(2,), limit=SPEED_LIMIT, saturate=False, in_unit="um", out_unit="um/s"),
        NormSaturation("clip", SPEED_LIMIT, shape=(2,), unit="um/s"),
        Integrator("plant", shape=(2,), in_unit="um/s", out_unit="um"),
        Delay("camera_delay", DELAY, shape=(2,), unit="um"),
    ]
    wires = [("ref.y", "err.u0"), ("err.y", "pi.e"), ("pi.u", "clip.u"), ("clip.y", "plant.u"),
             ("plant.y", "camera_delay.u")]
    if noise == "drawn":
        blocks.append(GaussianNoise("camera_noise", NOISE_SIGMA, shape=(2,), unit="um"))
        wires += [("camera_delay.y", "camera_noise.u"), ("camera_noise.y", "err.u1")]
        return Diagram("b1", blocks, wires, outputs={"p": "plant.y", "y": "camera_noise.y"})
    blocks.append(Sum("camera", "++", shape=(2,), unit="um"))
    wires += [("camera_delay.y", "camera.u0"), ("camera.y", "err.u1")]
    return Diagram("b1", blocks, wires, inputs={"n": "camera.u1"}, outputs={"p": "plant.y", "y": "camera.y"})


def b1_noise(seed: int, trials) -> np.ndarray:
    """Camera noise of the given trials, ``(B, 1800, 2)`` µm, exactly as the magctl diagram draws it."""
    streams = TrialStreams.for_block(seed, [int(k) for k in trials], "camera_noise")
    return np.stack([streams.standard_normal((2,), at=k) for k in range(STEPS)], axis=1) * NOISE_SIGMA


def b1_numpy(noise: np.ndarray) -> np.ndarray:
    """Hand-written loop vectorised across trials; returns ``p`` as ``(B, 1800, 2)``."""
    batch = noise.shape[0]
    r = np.asarray(REFERENCE)
    p = np.zeros((batch, 2))
    integ = np.zeros((batch, 2))
    past = np.zeros((DELAY, batch, 2))  # p[k-2], p[k-1]
    out = np.empty((batch, STEPS, 2))
    for k in range(STEPS):
        out[:, k] = p
        e = r - (past[0] + noise[:, k])
        u = KP * e + KI * integ
        speed = np.sqrt(np.einsum("bi,bi->b", u, u))
        over = speed > SPEED_LIMIT
        integ = integ + T * e * (~over)[:, None]
        u = u * np.where(over, SPEED_LIMIT / np.where(over, speed, 1.0), 1.0)[:, None]
        past[0], past[1] = past[1], p
        p = p + T * u
    return out


def b1_python_control(noise_one: np.ndarray) -> np.ndarray:
    """One trial with python-control's ``nlsys`` + ``interconnect`` + ``input_output_response``.

    ``noise_one`` is ``(1800, 2)``; returns ``p`` as ``(1800, 2)``.
    """

    def clip(u):
        n = np.hypot(u[0], u[1])
        return u * (SPEED_LIMIT / n) if n > SPEED_LIMIT else u

    plant = control.nlsys(
        lambda t, x, u, params: x + T * clip(u), lambda t, x, u, params: x,
        inputs=["u0", "u1"], outputs=["p0", "p1"], states=2, dt=T, name="plant",
    )
    # camera: two-step delay of p plus the noise input
    camera = control.nlsys(
        lambda t, x, u, params: np.array([x[2], x[3], u[0], u[1]]),
        lambda t, x, u, params: np.array([x[0] + u[2], x[1] + u[3]]),
        inputs=["p0", "p1", "n0", "n1"], outputs=["y0", "y1"], states=4, dt=T, name="camera",
    )
    r = np.asarray(REFERENCE)

    def pi_update(t, x, u, params):
        e = r - u
        cmd = KP * e + KI * x
        return x if np.hypot(cmd[0], cmd[1]) > SPEED_LIMIT else x + T * e

    controller = control.nlsys(
        pi_update, lambda t, x, u, params: KP * (r - u) + KI * x,
        inputs=["y0", "y1"], outputs=["u0", "u1"], states=2, dt=T, name="pi",
    )
    loop = control.interconnect(
        [plant, camera, controller], inplist=["n0", "n1"], outlist=["p0", "p1"], dt=T, name="b1",
    )
    timepts = np.arange(STEPS) * T
    resp = control.input_output_response(loop, timepts, noise_one.T, X0=0)
    return resp.outputs.T


# --- trial functions for sweeps ---------------------------------------------------------------------
def drift_diagram(speed: float = 100e-6, step_sigma: float = 20e-6, meas_sigma: float = 5e-6) -> Diagram:
    """A robot driven at a constant velocity whose step varies randomly, seen through a noisy camera.

    ``velocity = (speed, 0) + step_sigma·n₁``, ``position = Σ velocity·T``,
    ``measured = position + meas_sigma·n₂``, with ``n₁, n₂`` drawn from each
    trial's own streams.

    Parameters
    ----------
    speed : float
        Commanded speed along x in m/s.
    step_sigma : float
        Standard deviation of the per-frame velocity jitter in m/s.
    meas_sigma : float
        Standard deviation of the position measurement noise in m.
    """
    return Diagram(
        "drift",
        [
            Constant("cmd", [speed, 0.0], shape=(2,), unit="m/s"),
            GaussianNoise("jitter", step_sigma, shape=(2,), unit="m/s"),
            Integrator("pos", shape=(2,), in_unit="m/s", out_unit="m"),
            GaussianNoise("camera", meas_sigma, shape=(2,), unit="m"),
        ],
        [("cmd.y", "jitter.u"), ("jitter.y", "pos.u"), ("pos.y", "camera.u")],
        outputs={"position": "pos.y", "measured": "camera.y"},
    )


def drift_trials(trial_indices: Sequence[int], seed: int, *, steps: int = 60, speed: float = 100e-6,
                 step_sigma: float = 20e-6, meas_sigma: float = 5e-6) -> dict[str, np.ndarray]:
    """Run the trials ``trial_indices`` of :func:`drift_diagram` in lockstep.

    Returns
    -------
    dict
        ``final`` (B, 2) true end position in m, ``measured`` (B, steps, 2)
        camera trace in m, ``trial`` (B,) the global trial indices.
    """
    trials = [int(k) for k in trial_indices]
    res = simulate(drift_diagram(speed, step_sigma, meas_sigma), steps, batch=len(trials), seed=seed,
                   trials=trials)
    return {"final": res["position"][:, -1].copy(), "measured": res["measured"], "trial": np.asarray(trials)}


def failing_trials(trial_indices: Sequence[int], seed: int, *, fail_on: int = 0, **kwargs) -> dict[str, np.ndarray]:
    """:func:`drift_trials`, except that a batch holding trial ``fail_on`` raises ``ValueError``.

    Used to check that sweeps report which chunk of trials failed.
    """
    if int(fail_on) in {int(k) for k in trial_indices}:
        raise ValueError(f"trial {fail_on} hit a deliberate fault")
    return drift_trials(trial_indices, seed, **kwargs)
