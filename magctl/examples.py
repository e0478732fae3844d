"""Small, importable trial functions for :func:`magctl.sweep.run_trials`.

Functions handed to a process pool or a Dask worker are pickled by reference,
so they must live in an importable module (not in a test file or ``__main__``).
These are real magctl simulations, small enough for tests and documentation.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from magctl.core.diagram import Diagram
from magctl.core.linear import Constant, Integrator
from magctl.core.nonlinear import GaussianNoise
from magctl.core.simulate import simulate


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
