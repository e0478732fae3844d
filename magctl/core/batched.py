"""Batch-safe linear algebra: results for a trial never depend on the batch around it.

``X @ M`` on a ``(B, n)`` batch goes to BLAS, whose kernels block and vectorise
differently for different B, so row k of the product can differ in the last bit
between a batch of 1 and a batch of 1 000 — enough to break bit-for-bit trial
reproducibility after a few hundred steps of a chaotic contact simulation.
``numpy.einsum`` (without ``optimize``) sums each output element in a fixed
order, independent of the other rows.
"""

from __future__ import annotations

import numpy as np


def rows_times(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``x @ m`` for a batch of row vectors ``x (B, …, n)`` and a matrix ``(n, p)`` or vector ``(n,)``,
    computed per row so that each trial's result is independent of the batch."""
    if m.ndim == 1:
        return np.einsum("...i,i->...", x, m)
    return np.einsum("...i,ij->...j", x, m)


# --- planar vectors (…, 2), batch-safe: einsum sums each row on its own -----------------------------
def norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis."""
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def unit(v: np.ndarray, fallback=(1.0, 0.0)) -> np.ndarray:
    """Unit vectors along the last axis (``fallback`` where the vector is zero)."""
    n = norm(v)[..., None]
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), np.asarray(fallback, dtype=float))


def perp(v: np.ndarray) -> np.ndarray:
    """``v`` rotated by +90°."""
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)

