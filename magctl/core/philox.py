"""Counter-based random numbers: Philox4x32-10, addressed by (seed, trial, block, step, draw).

A counter-based generator maps a counter and a key straight to random bits (Salmon, Moraes, Dror and
Shaw, "Parallel random numbers: as easy as 1, 2, 3", SC 2011; the Random123 library). The k-th draw
of a stream needs no sequential state, so every trial of every block reads its numbers at any step in
any order: trial ``t``'s draws do not depend on the batch size, the chunking of trials between
processes, or the engine, and drawing needs no generator set-up and no tables.

Addressing, one Philox block of four 32-bit words per call:

* key ``(k0, k1)``: the run's seed (its low and high 32 bits);
* counter ``(c0, c1, c2, c3)``: the step (position) ``p``; the draw's kind in the top bits of ``c1``
  and its element pair ``i // 2`` below; the global trial index; the block's key (a CRC-32 of its
  path in the diagram, :func:`magctl.core.random.block_key`).

A stream key row is ``(k0, k1, trial, block, on)`` (``uint64``). A row with ``on = 0`` is a stream
switched off — the noise-free path a linearisation runs: normals read 0 and uniforms 1, so a draw
``u < p`` never fires.

Normals come from the Box–Muller transform of two 53-bit uniforms (one Philox block gives the pair
``i``, ``i + 1``); uniforms are 53-bit, in [0, 1). Checked against Random123's published known-answer
vectors and by distribution tests (``tests/core/test_random.py``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")

_MASK = np.uint64(0xFFFFFFFF)
_M0 = np.uint64(0xD2511F53)
_M1 = np.uint64(0xCD9E8D57)
_W0 = np.uint64(0x9E3779B9)
_W1 = np.uint64(0xBB67AE85)
_S32 = np.uint64(32)
_S11 = np.uint64(11)
_KIND_SHIFT = np.uint64(28)

NORMAL = 0
"""Kind of a draw of standard normals (counter word ``c1``'s top bits)."""
UNIFORM = 1
"""Kind of a draw of U[0, 1) numbers."""
LARGE_NORMAL = 2
"""Kind of a whole image of standard normals drawn at once (the rendered camera's sensor noise)."""

KEY_WIDTH = 5
"""Columns of a stream key row: k0, k1, trial, block, on."""

_TWO_PI = 2.0 * math.pi
_INV53 = 1.0 / 9007199254740992.0   # 2⁻⁵³


@jit
def philox4x32(c0, c1, c2, c3, k0, k1):
    """Philox4x32-10 of the counter ``(c0, c1, c2, c3)`` under the key ``(k0, k1)``: four 32-bit words
    (each held in a ``uint64``), as Random123's ``philox4x32_R(10, ctr, key)``."""
    c0, c1, c2, c3 = c0 & _MASK, c1 & _MASK, c2 & _MASK, c3 & _MASK
    k0, k1 = k0 & _MASK, k1 & _MASK
    for r in range(10):
        if r > 0:
            k0 = (k0 + _W0) & _MASK
            k1 = (k1 + _W1) & _MASK
        p0 = _M0 * c0
        p1 = _M1 * c2
        c0, c1, c2, c3 = ((p1 >> _S32) ^ c1 ^ k0), p1 & _MASK, ((p0 >> _S32) ^ c3 ^ k1), p0 & _MASK
    return c0, c1, c2, c3


@jit
def _block(key, b, position, kind, pair):
    return philox4x32(np.uint64(position), (np.uint64(kind) << _KIND_SHIFT) | np.uint64(pair),
                      key[b, 2], key[b, 3], key[b, 0], key[b, 1])


@jit
def _unit(hi, lo):
    """A 53-bit uniform in [0, 1) from two 32-bit words."""
    return float(((hi << _S32) | lo) >> _S11) * _INV53


@jit
def normal(key, b, position, index):
    """Standard normal number ``index`` of trial row ``b``'s stream at step ``position``."""
    if key[b, 4] == 0:
        return 0.0
    w0, w1, w2, w3 = _block(key, b, position, NORMAL, index >> 1)
    r = math.sqrt(-2.0 * math.log(1.0 - _unit(w0, w1)))     # 1 − u ∈ (0, 1]: the log stays finite
    a = _TWO_PI * _unit(w2, w3)
    return r * math.cos(a) if index % 2 == 0 else r * math.sin(a)


@jit
def uniform(key, b, position, index):
    """U[0, 1) number ``index`` of trial row ``b``'s stream at step ``position`` (1.0 when the stream is off)."""
    if key[b, 4] == 0:
        return 1.0
    w0, w1, w2, w3 = _block(key, b, position, UNIFORM, index >> 1)
    return _unit(w0, w1) if index % 2 == 0 else _unit(w2, w3)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_normal(key, position, out):
    """``out[b, i]`` = normal ``i`` of row ``b`` at ``position``, pairs computed once (``out``: ``(B, n)``)."""
    for b in range(out.shape[0]):
        n = out.shape[1]
        if key[b, 4] == 0:
            for i in range(n):
                out[b, i] = 0.0
            continue
        for j in range((n + 1) // 2):
            w0, w1, w2, w3 = _block(key, b, position, NORMAL, j)
            r = math.sqrt(-2.0 * math.log(1.0 - _unit(w0, w1)))
            a = _TWO_PI * _unit(w2, w3)
            out[b, 2 * j] = r * math.cos(a)
            if 2 * j + 1 < n:
                out[b, 2 * j + 1] = r * math.sin(a)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_uniform(key, position, out):
    """``out[b, i]`` = uniform ``i`` of row ``b`` at ``position`` (``out``: ``(B, n)``)."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = uniform(key, b, position, i)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_large_normal(key, b, position, out):
    """A flat array of standard normals for row ``b`` at ``position``: an image's worth, its own kind."""
    n = out.shape[0]
    for j in range((n + 1) // 2):
        w0, w1, w2, w3 = _block(key, b, position, LARGE_NORMAL, j)
        r = math.sqrt(-2.0 * math.log(1.0 - _unit(w0, w1)))
        a = _TWO_PI * _unit(w2, w3)
        out[2 * j] = r * math.cos(a)
        if 2 * j + 1 < n:
            out[2 * j + 1] = r * math.sin(a)
