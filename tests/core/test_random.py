"""Counter-based per-trial streams: Philox4x32-10 against Random123's published answers, draws that depend on
their address only, and distributions checked by scipy's tests."""

import numpy as np
import pytest
from scipy import stats

from magctl.core.errors import MagctlError
from magctl.core.philox import philox4x32
from magctl.core.random import TrialStreams, stream_keys

# Random123 (DEShawResearch/random123), tests/kat_vectors, the three "philox4x32 10" lines:
# counter (4 words), key (2 words), expected output (4 words)
KAT = [
    ((0x00000000,) * 4, (0x00000000,) * 2, (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    ((0xFFFFFFFF,) * 4, (0xFFFFFFFF,) * 2, (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD)),
    ((0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344), (0xA4093822, 0x299F31D0),
     (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1)),
]


@pytest.mark.parametrize("counter, key, expected", KAT)
def test_philox_matches_the_published_known_answers(counter, key, expected):
    got = philox4x32(*(np.uint64(c) for c in counter), *(np.uint64(k) for k in key))
    assert tuple(int(w) for w in got) == expected


def test_a_trials_draws_do_not_depend_on_the_batch_or_the_order_of_reading():
    batch = TrialStreams.for_block(4, [0, 7, 3], "cam")
    alone = TrialStreams.for_block(4, [7], "cam")
    late = [batch.standard_normal((5,), at=k) for k in range(40)]
    for k in reversed(range(40)):               # backwards, one trial alone: the same numbers
        assert np.array_equal(alone.standard_normal((5,), at=k)[0], late[k][1])
    assert np.array_equal(batch.random((2,), at=12), batch.random((2,), at=12))


def test_streams_differ_by_seed_block_trial_step_and_kind():
    base = TrialStreams.for_block(1, [0], "cam").standard_normal((4,), at=3)
    for other in (TrialStreams.for_block(2, [0], "cam").standard_normal((4,), at=3),
                  TrialStreams.for_block(1, [0], "robot").standard_normal((4,), at=3),
                  TrialStreams.for_block(1, [1], "cam").standard_normal((4,), at=3),
                  TrialStreams.for_block(1, [0], "cam").standard_normal((4,), at=4),
                  TrialStreams.for_block(1, [0], "cam").random((4,), at=3)):
        assert not np.any(other == base)


def test_normals_are_standard_normal_and_uncorrelated():
    streams = TrialStreams.for_block(2026, range(400), "noise")
    draws = np.stack([streams.standard_normal((6,), at=k) for k in range(100)], axis=1)   # (400, 100, 6)
    flat = draws.ravel()
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    assert abs(flat.mean()) < 4 / np.sqrt(flat.size)
    assert abs(flat.var() - 1) < 4 * np.sqrt(2 / flat.size)
    # the two normals of one Box–Muller pair, neighbouring steps and neighbouring trials are independent
    pairs = ((draws[..., 0], draws[..., 1]), (draws[:, :-1, 2], draws[:, 1:, 2]), (draws[:-1, :, 3], draws[1:, :, 3]))
    for a, b in pairs:
        r = np.corrcoef(a.ravel(), b.ravel())[0, 1]
        assert abs(r) < 5 / np.sqrt(a.size)


def test_uniforms_are_uniform_on_the_half_open_unit_interval():
    streams = TrialStreams.for_block(9, range(300), "drops")
    u = np.stack([streams.random((3,), at=k) for k in range(100)]).ravel()
    assert u.min() >= 0.0 and u.max() < 1.0
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    counts = np.histogram(u, bins=20, range=(0, 1))[0]
    assert stats.chisquare(counts).pvalue > 1e-3


def test_a_stream_switched_off_reads_the_noise_free_path():
    from magctl.core.philox import fill_normal, fill_uniform

    keys = stream_keys(3, [0, 1], 5, on=False)
    n, u = np.full((2, 3), np.nan), np.full((2, 3), np.nan)
    fill_normal(keys, 7, n)
    fill_uniform(keys, 7, u)
    assert np.all(n == 0.0) and np.all(u == 1.0)


def test_large_draws_depend_on_trial_and_step_only():
    a = TrialStreams.for_block(1, [5, 6], "cam")
    b = TrialStreams.for_block(1, [6], "cam")
    img = a.large("standard_normal", 1, (4, 5), at=9)
    assert np.array_equal(img, b.large("standard_normal", 0, (4, 5), at=9))
    assert np.array_equal(img, a.large("standard_normal", 1, (4, 5), at=9))
    assert not np.array_equal(img, a.large("standard_normal", 1, (4, 5), at=10))
    assert not np.any(img.ravel()[:6] == a.standard_normal((6,), at=9)[1])


def test_addresses_out_of_range_are_refused_by_name():
    with pytest.raises(MagctlError, match="seed"):
        TrialStreams.for_block(-1, [0], "cam")
    with pytest.raises(MagctlError, match="trial"):
        TrialStreams.for_block(0, [2**32], "cam")
    with pytest.raises(MagctlError, match="position"):
        TrialStreams.for_block(0, [0], "cam").standard_normal((), at=-1)
