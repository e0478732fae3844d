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
