"""Benchmark B1's three implementations agree to 1e-6 µm on the same seeds."""

import numpy as np

from magctl.core import simulate
from magctl.testing import REFERENCE, STEPS, b1_diagram, b1_noise, b1_numpy, b1_python_control


def test_three_implementations_agree():
    seed, trials = 5, [0, 7]
    noise = b1_noise(seed, trials)
    numpy_p = b1_numpy(noise)
    magctl_p = simulate(b1_diagram(), STEPS, batch=2, seed=seed, trials=trials, record=[])["p"]
    fed_p = simulate(b1_diagram("input"), STEPS, batch=2, seed=seed, inputs={"n": noise}, record=[],
                     engine="compiled")["p"]
    control_p = b1_python_control(noise[1])
    assert np.abs(magctl_p - numpy_p).max() < 1e-6
    assert np.abs(fed_p - numpy_p).max() < 1e-6
    assert np.abs(control_p - numpy_p[1]).max() < 1e-6
    # the loop actually reaches the reference and saturates on the way (speed ≤ 400 µm/s)
    assert np.allclose(numpy_p[:, -1], REFERENCE, atol=20)
    speed = np.linalg.norm(np.diff(numpy_p, axis=1), axis=2) * 30
    assert speed.max() <= 400 + 1e-9
    assert speed.max() > 399
