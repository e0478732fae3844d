"""Typed ports: a name, a per-trial shape and a unit.

Every array on a port carries a leading trial axis, so a port of shape ``(2,)``
holds arrays shaped ``(B, 2)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DIMENSIONLESS = "1"


@dataclass(frozen=True)
class Port:
    """A named, typed block port.

    Parameters
    ----------
    name : str
        Port name, unique among the block's inputs (or outputs).
    shape : tuple of int
        Shape of one trial's value; the batch axis is not included.
    unit : str
        SI unit of the value (``"m"``, ``"m/s"``, ``"rad"``, ``"T"``, ``"A"``, ``"1"``…).
        Connected ports must carry the same unit.
    dtype : str
        ``"float64"`` for signals, ``"bool"`` for flags (saturation, tracking loss).
    """

    name: str
    shape: tuple[int, ...] = ()
    unit: str = DIMENSIONLESS
    dtype: str = "float64"

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"port name {self.name!r} must be a Python identifier")
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))

    @property
    def size(self) -> int:
        """Number of scalar elements per trial."""
        return int(np.prod(self.shape, dtype=int))

    def empty(self, batch: int) -> np.ndarray:
        """Zeros with this port's shape and dtype for ``batch`` trials."""
        return np.zeros((batch, *self.shape), dtype=self.dtype)

    def describe(self) -> str:
        return f"{self.name}{list(self.shape)}[{self.unit}]"


def port(name: str, shape=(), unit: str = DIMENSIONLESS, dtype: str = "float64") -> Port:
    """Shorthand constructor used by block definitions."""
    return Port(name, tuple(shape) if not isinstance(shape, int) else (shape,), unit, dtype)
