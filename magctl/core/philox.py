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

Normals come from the ziggurat method (Marsaglia and Tsang, "The ziggurat method for generating random
variables", J. Stat. Softw. 5(8), 2000; 256 layers, in Doornik's form with a 53-bit uniform, ZIGNOR 2005):
one 64-bit half of a Philox block gives normal ``i`` (the block gives the pair ``i``, ``i + 1``), and the
rare rejections (about 1 %) read further blocks of their own kind. Uniforms are 53-bit, in [0, 1).
Checked against Random123's published known-answer vectors and by distribution tests
(``tests/core/test_random.py``).
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
RETRY = 8
"""First kind of the blocks a rejected ziggurat draw reads (kind ``RETRY + attempt``, up to 7 attempts)."""
_INDEX_BITS = np.uint64(20)
_INDEX_MASK = np.uint64((1 << 20) - 1)

ZIGGURAT_R = 3.6541528853610088
"""Start of the tail of the 256-layer ziggurat (Marsaglia and Tsang 2000, Table 1); every layer has the
area ``ZIGGURAT_V = r·f(r) + ∫_r^∞ f`` under ``f(x) = exp(−x²/2)`` (checked in the tests)."""


def _ziggurat_tables(n: int = 256, r: float = ZIGGURAT_R) -> tuple[np.ndarray, np.ndarray]:
    """Layer edges ``x[0] = v/f(r), x[1] = r, …, x[n] = 0`` and ``f(x[i])``: Doornik's recurrence
    ``x[i+1] = sqrt(−2 ln(v/x[i] + f(x[i])))``."""
    v = r * math.exp(-0.5 * r * r) + math.sqrt(0.5 * math.pi) * math.erfc(r / math.sqrt(2.0))
    x = np.empty(n + 1)
    x[0], x[1], x[n] = v / math.exp(-0.5 * r * r), r, 0.0
    for i in range(1, n - 1):
        x[i + 1] = math.sqrt(-2.0 * math.log(v / x[i] + math.exp(-0.5 * x[i] * x[i])))
    return x, np.exp(-0.5 * x * x)


_ZX, _ZF = _ziggurat_tables()
_ZR = ZIGGURAT_R

KEY_WIDTH = 5
"""Columns of a stream key row: k0, k1, trial, block, on."""

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
def _ziggurat(key, b, position, kind, index, hi, lo):
    """A standard normal from the 64-bit word ``hi:lo``: its top 53 bits the uniform, its low 8 bits the layer;
    a rejection reads the blocks ``RETRY + a`` of draw ``index`` (Doornik's ZIGNOR)."""
    for attempt in range(8):
        u = 2.0 * _unit(hi, lo) - 1.0
        layer = lo & np.uint64(0xFF)
        x = u * _ZX[layer]
        if abs(x) < _ZX[layer + 1]:           # inside the layer's rectangle: ~99 % of draws
            return x
        w0, w1, w2, w3 = _block(key, b, position, RETRY + attempt,
                                (np.uint64(kind) << _INDEX_BITS) | (np.uint64(index) & _INDEX_MASK))
        if layer == 0:                          # the tail beyond r
            while True:
                t = -math.log(1.0 - _unit(w0, w1)) / _ZR
                y = -math.log(1.0 - _unit(w2, w3))
                if 2.0 * y > t * t:
                    return _ZR + t if u > 0 else -(_ZR + t)
                w0, w1, w2, w3 = philox4x32(w0, w1, w2, w3, key[b, 0], key[b, 1])
        if _ZF[layer + 1] + _unit(w2, w3) * (_ZF[layer] - _ZF[layer + 1]) < math.exp(-0.5 * x * x):
            return x
        hi, lo = w0, w1
    return x


@jit
def normal_pair(key, b, position, pair):
    """Standard normals ``2·pair`` and ``2·pair + 1`` of trial row ``b``'s stream at step ``position``
    (0, 0 when the stream is off): one Philox block for both."""
    if key[b, 4] == 0:
        return 0.0, 0.0
    w0, w1, w2, w3 = _block(key, b, position, NORMAL, pair)
    return (_ziggurat(key, b, position, NORMAL, 2 * pair, w0, w1),
            _ziggurat(key, b, position, NORMAL, 2 * pair + 1, w2, w3))


@jit
def normal(key, b, position, index):
    """Standard normal number ``index`` of trial row ``b``'s stream at step ``position`` (0 when off)."""
    z0, z1 = normal_pair(key, b, position, index >> 1)
    return z0 if index % 2 == 0 else z1


@jit
def uniform(key, b, position, index):
    """U[0, 1) number ``index`` of trial row ``b``'s stream at step ``position`` (1.0 when the stream is off)."""
    if key[b, 4] == 0:
        return 1.0
    w0, w1, w2, w3 = _block(key, b, position, UNIFORM, index >> 1)
    return _unit(w0, w1) if index % 2 == 0 else _unit(w2, w3)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_normal(key, position, out):
    """``out[b, i]`` = normal ``i`` of row ``b`` at ``position``, each pair computed once (``out``: ``(B, n)``)."""
    n = out.shape[1]
    for b in range(out.shape[0]):
        for j in range((n + 1) // 2):
            z0, z1 = normal_pair(key, b, position, j)
            out[b, 2 * j] = z0
            if 2 * j + 1 < n:
                out[b, 2 * j + 1] = z1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_uniform(key, position, out):
    """``out[b, i]`` = uniform ``i`` of row ``b`` at ``position`` (``out``: ``(B, n)``)."""
    for b in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[b, i] = uniform(key, b, position, i)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def fill_large_normal(key, b, position, out):
    """A flat array of standard normals for row ``b`` at ``position``: an image's worth, a kind of its own."""
    n = out.shape[0]
    for j in range((n + 1) // 2):
        w0, w1, w2, w3 = _block(key, b, position, LARGE_NORMAL, j)
        out[2 * j] = _ziggurat(key, b, position, LARGE_NORMAL, 2 * j, w0, w1)
        if 2 * j + 1 < n:
            out[2 * j + 1] = _ziggurat(key, b, position, LARGE_NORMAL, 2 * j + 1, w2, w3)
