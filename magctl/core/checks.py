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
