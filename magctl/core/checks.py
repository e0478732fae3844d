"""Validation of user-supplied numbers: one clear :class:`MagctlError` naming the parameter."""

from __future__ import annotations

import numpy as np

from magctl.core.errors import MagctlError


def check_positive(name: str, value: float, allow_zero: bool = False) -> float:
    """``value`` as a float, or a :class:`MagctlError` naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise MagctlError(f"{name}={value!r} is not a number") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise MagctlError(f"{name}={value!r} must be {'non-negative' if allow_zero else 'positive'} and finite")
    return v


def check_finite(name: str, value) -> float:
    """``value`` as a finite float, or a :class:`MagctlError` naming ``name``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise MagctlError(f"{name}={value!r} is not a number") from None
    if not np.isfinite(v):
        raise MagctlError(f"{name}={value!r} must be finite")
    return v


def check_whole(name: str, value, low: int, high: int | None = None, error=MagctlError) -> int:
    """``value`` as an int in ``[low, high)`` — an integer, or a float only when whole (counts, seeds are never
    truncated) — or ``error`` naming ``name`` and the range."""
    whole = (isinstance(value, (int, np.integer)) and not isinstance(value, bool)) or (
        isinstance(value, (float, np.floating)) and bool(np.isfinite(value)) and float(value).is_integer())
    if not whole or value < low or (high is not None and value >= high):
        span = f">= {low}" if high is None else f"in [{low}, {high})" if high != 2**64 else f"in [{low}, 2**64)"
        raise error(f"{name} must be a whole number {span}, got {value!r}")
    return int(value)
