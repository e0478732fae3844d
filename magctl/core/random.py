"""Per-trial random streams that do not depend on the batch size, the chunking or the engine.

Every draw is a function of its address — the run's seed, the global trial index, the block (a
stable hash of its path in the diagram), the step and the draw's index — through the counter-based
generator of :mod:`magctl.core.philox`. Trial ``k``'s numbers are therefore the same whether it ran
alone, in a batch of 10 000, in another process, interpreted or compiled; a block reads its stream
*by position* (the step count it keeps in its state), so ``output`` and ``update`` stay functions of
the state and an old state re-evaluated sees the same numbers. Nothing is drawn ahead or kept.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

from magctl.core.checks import check_whole
from magctl.core.errors import MagctlError

_U64 = 1 << 64


def trial_seed_sequence(seed: int, trial: int) -> np.random.SeedSequence:
    """The seed sequence of global trial ``trial``: ``SeedSequence(seed).spawn(n)[trial]`` (for code that
    wants a numpy ``Generator`` per trial, such as a sweep's trial function)."""
    return np.random.SeedSequence(int(seed), spawn_key=(int(trial),))


def block_key(path: str) -> int:
    """Stable 32-bit key of a block path."""
    return zlib.crc32(path.encode())


def check_seed(seed) -> int:
    """A root seed: a whole number in ``[0, 2**64)`` (a float only when whole), or a :class:`MagctlError`."""
    return check_whole("seed", seed, 0, _U64)


def stream_keys(seed: int, trials: Sequence[int], block: int, on: bool = True) -> np.ndarray:
    """The key rows ``(k0, k1, trial, block, on)`` (``uint64``, :mod:`magctl.core.philox`) of the given
    global trials of one block's streams."""
    seed = check_seed(seed)
    trials = np.asarray(list(trials), dtype=np.int64).reshape(-1)
    if trials.size and (trials.min() < 0 or trials.max() >= 1 << 32):
        raise MagctlError("trial indices must lie in [0, 2**32)")
    keys = np.empty((trials.size, 5), dtype=np.uint64)
    keys[:, 0] = seed & 0xFFFFFFFF
    keys[:, 1] = seed >> 32
    keys[:, 2] = trials
    keys[:, 3] = int(block) & 0xFFFFFFFF
    keys[:, 4] = 1 if on else 0
    return keys


class TrialStreams:
    """One block's per-trial random streams, read by position.

    Parameters
    ----------
    seed : int
        The run's seed, in [0, 2⁶⁴).
    trials : sequence of int
        Global trial index of each batch row.
    block : int
        The block's key (:func:`block_key` of its path; 0 for streams not tied to a block).
    """

    def __init__(self, seed: int, trials: Sequence[int], block: int = 0):
        self.seed = int(seed)
        self.trials = [int(k) for k in trials]
        self.block = int(block)
        self.keys = stream_keys(self.seed, self.trials, self.block)
        """``(B, 5)`` key rows, what a kernel reads its draws from."""
        self._generators = None

    @classmethod
    def for_block(cls, seed: int, trials: Sequence[int], path: str) -> TrialStreams:
        """Streams of block ``path`` for the given global trial indices."""
        return cls(seed, trials, block_key(path))

    @classmethod
    def for_trials(cls, seed: int, trials: Sequence[int]) -> TrialStreams:
        """Streams keyed by the trials alone (no block)."""
        return cls(seed, trials, 0)

    @property
    def batch(self) -> int:
        return len(self.trials)

    def standard_normal(self, shape: tuple[int, ...] = (), *, at: int) -> np.ndarray:
        """Step ``at``'s N(0, 1) draws, ``(B, *shape)``: the same numbers for every call with the same ``at``."""
        from magctl.core.philox import fill_normal

        out = np.empty((self.batch, int(np.prod(shape, dtype=int))))
        fill_normal(self.keys, _position(at), out)
        return out.reshape((self.batch, *shape))

    def random(self, shape: tuple[int, ...] = (), *, at: int) -> np.ndarray:
        """Step ``at``'s U[0, 1) draws, ``(B, *shape)``."""
        from magctl.core.philox import fill_uniform

        out = np.empty((self.batch, int(np.prod(shape, dtype=int))))
        fill_uniform(self.keys, _position(at), out)
        return out.reshape((self.batch, *shape))

    def large(self, kind: str, trial: int, shape: tuple[int, ...], at: int) -> np.ndarray:
        """Standard normals of ``shape`` for batch row ``trial`` at step ``at``, too many to draw for every
        trial at once (a rendered frame's sensor noise); a draw kind of their own."""
        from magctl.core.philox import fill_large_normal

        if kind != "standard_normal":
            raise MagctlError(f"large draws are standard normals, not {kind!r}")
        out = np.empty(int(np.prod(shape, dtype=int)))
        fill_large_normal(self.keys, int(trial), _position(at), out)
        return out.reshape(shape)

    @property
    def generators(self) -> list[np.random.Generator]:
        """One numpy ``Generator`` per trial, seeded by (seed, trial, block): for Python blocks that draw an
        unknown number of values per step (the particle filter)."""
        if self._generators is None:
            self._generators = [np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(k, self.block)))
                                for k in self.trials]
        return self._generators


def _position(at) -> int:
    at = int(at)
    if at < 0 or at >= 1 << 32:
        raise MagctlError(f"random stream position {at} must lie in [0, 2**32)")
    return at
