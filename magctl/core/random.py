"""Per-trial random streams that do not depend on the batch size.

Trial ``k`` of a run seeded with ``seed`` draws from
``SeedSequence(seed, spawn_key=(k,))`` — the same sequence
``SeedSequence(seed).spawn(n)[k]`` gives for any ``n > k`` — so its result is
the same whether it ran alone, in a batch of 10 000, or in another process.
Each block gets its own child of the trial's sequence, keyed by a stable hash
of the block's path in the diagram.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

from magctl.core.errors import MagctlError


def trial_seed_sequence(seed: int, trial: int) -> np.random.SeedSequence:
    """The seed sequence of global trial ``trial``: ``SeedSequence(seed).spawn(n)[trial]``."""
    return np.random.SeedSequence(int(seed), spawn_key=(int(trial),))


LARGE = 0x4C415247
"""Spawn-key element of the per-step streams of :meth:`TrialStreams.large`."""


def block_key(path: str) -> int:
    """Stable 32-bit key of a block path, used as a spawn key."""
    return zlib.crc32(path.encode())


class TrialStreams:
    """One numpy ``Generator`` per trial, drawn in fixed-size chunks.

    Drawing ``shape`` per step for every trial would call B generators each
    step; instead each trial draws ``chunk`` steps at once and the stream
    serves them step by step. Chunked draws from a ``Generator`` are the same
    numbers as one large draw, so trial ``k``'s values never depend on ``B``.

    Blocks draw *by position* (``at=`` the step count held in their state): a
    stream is then a memo of its sequence, not hidden state, and re-evaluating
    an old state (a finite difference, a contract test) sees the same numbers.

    Parameters
    ----------
    generators : sequence of numpy.random.Generator
        One per trial, in batch order.
    chunk : int
        Steps drawn per refill.
    """

    def __init__(self, generators: Sequence[np.random.Generator], chunk: int = 256,
                 sequences: Sequence[np.random.SeedSequence] | None = None):
        self.generators = list(generators)
        self.sequences = None if sequences is None else list(sequences)
        self.chunk = int(chunk)
        self._buffers: dict[tuple, list] = {}
        self._memo: dict[tuple, list] = {}
        self.compiled_position = 0
        """Positions the compiled engine has drawn from these streams' seed sequences (it does not
        move the generators, so the memo cannot start after them)."""

    @classmethod
    def for_block(cls, seed: int, trials: Sequence[int], path: str, chunk: int = 256) -> TrialStreams:
        """Streams of block ``path`` for the given global trial indices."""
        key = block_key(path)
        seqs = [np.random.SeedSequence(int(seed), spawn_key=(int(k), key)) for k in trials]
        return cls([np.random.default_rng(q) for q in seqs], chunk, seqs)

    @classmethod
    def for_trials(cls, seed: int, trials: Sequence[int], chunk: int = 256) -> TrialStreams:
        """Streams seeded directly by each trial's sequence (no block key)."""
        seqs = [trial_seed_sequence(seed, k) for k in trials]
        return cls([np.random.default_rng(q) for q in seqs], chunk, seqs)

    @property
    def batch(self) -> int:
        return len(self.generators)

    def _draw(self, kind: str, shape: tuple[int, ...]) -> np.ndarray:
        key = (kind, shape)
        entry = self._buffers.get(key)
        if entry is None:
            entry = self._buffers[key] = [np.empty((self.batch, self.chunk, *shape)), self.chunk]
        buf, pos = entry
        if pos >= self.chunk:
            draw = getattr(np.random.Generator, kind)
            for b, g in enumerate(self.generators):
                draw(g, out=buf[b])
            pos = 0
        entry[1] = pos + 1
        return buf[:, pos]

    def _refill(self, kind: str, shape: tuple[int, ...]) -> np.ndarray:
        buf = np.empty((self.batch, self.chunk, *shape))
        draw = getattr(np.random.Generator, kind)
        for b, g in enumerate(self.generators):
            draw(g, out=buf[b])
        return buf

    def _draw_at(self, kind: str, shape: tuple[int, ...], at: int) -> np.ndarray:
        # memo [start, chunk, previous chunk]: positions start-chunk … start+chunk-1 are served
        key = (kind, shape)
        entry = self._memo.get(key)
        if entry is None:
            if self.compiled_position and at > 0:
                raise MagctlError(
                    f"random stream asked for step {at} after the compiled engine drew its steps up to "
                    f"{self.compiled_position}; continue it with engine='compiled'")
            entry = self._memo[key] = [at, self._refill(kind, shape), None]
        off = at - entry[0]
        if 0 <= off < self.chunk:
            return entry[1][:, off]
        while off >= self.chunk:
            entry[0] += self.chunk
            entry[2], entry[1] = entry[1], self._refill(kind, shape)
            off -= self.chunk
        if off >= 0:
            return entry[1][:, off]
        if off >= -self.chunk and entry[2] is not None:
            return entry[2][:, off + self.chunk]
        raise MagctlError(
            f"random stream asked for step {at}, but it has moved on to steps {entry[0]}…; a state can be "
            f"re-evaluated only within {self.chunk} steps of the newest one drawn"
        )

    def standard_normal(self, shape: tuple[int, ...] = (), at: int | None = None) -> np.ndarray:
        """One step of N(0, 1) draws, shaped ``(B, *shape)``.

        With ``at`` the draws are those of step ``at`` of this stream: the same
        array for every call with the same ``at`` (so a block's ``output`` and
        ``update`` stay functions of its state, which holds the step count), and
        the same numbers the sequential form gives at its ``at``-th call when the
        first positional call is ``at = 0``.
        """
        if at is None:
            return self._draw("standard_normal", tuple(shape))
        return self._draw_at("standard_normal", tuple(shape), int(at))

    def random(self, shape: tuple[int, ...] = (), at: int | None = None) -> np.ndarray:
        """One step of U[0, 1) draws, shaped ``(B, *shape)``; ``at`` as in :meth:`standard_normal`."""
        if at is None:
            return self._draw("random", tuple(shape))
        return self._draw_at("random", tuple(shape), int(at))

    def large(self, kind: str, trial: int, shape: tuple[int, ...], at: int) -> np.ndarray:
        """Draws of ``shape`` for batch row ``trial`` at step ``at``, too large to chunk (a noise image).

        They come from their own stream, ``SeedSequence(…, spawn_key=(…, LARGE, at))`` below
        the trial's, so they are a function of ``(trial, at)`` and leave the chunked streams alone.
        """
        if self.sequences is None:
            raise MagctlError("these streams were made from generators, not seed sequences: no large draws")
        seq = self.sequences[trial]
        gen = np.random.default_rng(np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, LARGE, int(at))))
        return getattr(gen, kind)(tuple(shape))

