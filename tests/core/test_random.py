"""Per-trial streams read by position: the same numbers as sequential draws, repeatable, bounded memory."""

import numpy as np
import pytest

from magctl.core.errors import MagctlError
from magctl.core.random import TrialStreams


def test_positional_draws_are_the_sequential_ones_and_repeat():
    seq = TrialStreams.for_block(4, [0, 7], "cam", chunk=8)
    pos = TrialStreams.for_block(4, [0, 7], "cam", chunk=8)
    want = [(seq.standard_normal((3,)).copy(), seq.random((1,)).copy()) for _ in range(30)]
    for k in range(30):
        n, r = pos.standard_normal((3,), at=k), pos.random((1,), at=k)
        assert np.array_equal(n, want[k][0]) and np.array_equal(r, want[k][1])
        assert np.array_equal(pos.standard_normal((3,), at=k), n)          # the same step again
    assert np.array_equal(pos.standard_normal((3,), at=20), want[20][0])   # back into the previous chunk
    with pytest.raises(MagctlError, match="moved on"):
        pos.standard_normal((3,), at=3)


def test_large_draws_depend_on_trial_and_step_only():
    a = TrialStreams.for_block(1, [5, 6], "cam")
    b = TrialStreams.for_block(1, [6], "cam")
    img = a.large("standard_normal", 1, (4, 5), at=9)
    assert np.array_equal(img, b.large("standard_normal", 0, (4, 5), at=9))
    assert np.array_equal(img, a.large("standard_normal", 1, (4, 5), at=9))
    assert not np.array_equal(img, a.large("standard_normal", 1, (4, 5), at=10))
