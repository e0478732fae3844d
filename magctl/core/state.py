"""A block's state, declared: :class:`StateVar` entries, nested member states and the helpers that walk them.

A block's state is a ``dict`` whose entries the block declares (:meth:`magctl.core.block.Block.state_vars`): arrays
with a leading trial axis, a few batch-wide counters, a member block's state nested as a dict (:data:`SUBSTATE`),
and, for blocks that draw noise, a :class:`~magctl.core.random.TrialStreams` read by position (:data:`STREAM`).
The blocks (:mod:`magctl.core.block`, which re-exports every name here), the kernels' state layout
(:mod:`magctl.core.kernel`), the linearisation and the engines read the same declarations. This module imports no
other of magctl's, so the kernels' layout reads it without importing the blocks that run the kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

State = dict

STREAM = "stream"
"""``StateVar.dtype`` of a per-trial random stream (:class:`~magctl.core.random.TrialStreams`)."""

SUBSTATE = "state"
"""``StateVar.dtype`` of a nested state dict (a member block's state), declared by ``StateVar.sub``."""


@dataclass(frozen=True)
class StateVar:
    """One declared entry of a block's state.

    Parameters
    ----------
    name : str
        Key in the state dict.
    shape : tuple of int
        Shape of one trial's value (without the trial axis).
    dtype : str
        ``"float64"``, ``"int64"``, ``"bool"``; :data:`STREAM` for a random stream,
        :data:`SUBSTATE` for a nested state dict, ``"object"`` for anything else a
        block keeps (never modified in place either).
    symbol : str
        The symbol the model's equations use (``"I"``, ``"x̂"``, ``"i_L"`` …).
    description : str
        What the entry holds, with its unit.
    batched : bool
        True: an array ``(B, *shape)``. False: one value for the whole batch (a
        step counter), ``shape`` then being its own shape.
    sub : tuple of StateVar
        With ``dtype=SUBSTATE``: the entries of the nested dict (a member block's state).
    """

    name: str
    shape: tuple[int, ...] = ()
    dtype: str = "float64"
    symbol: str = ""
    description: str = ""
    batched: bool = True
    sub: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))
        object.__setattr__(self, "sub", tuple(self.sub))
        if self.sub and self.dtype != SUBSTATE:
            raise ValueError(f"state entry {self.name!r}: 'sub' goes with dtype={SUBSTATE!r}")

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    @property
    def real(self) -> bool:
        """A per-trial real value: part of the state vector of a linearisation.

        Integers, flags, batch-wide counters and random streams are not: a
        linearisation holds them at their operating values.
        """
        return self.batched and self.dtype not in (STREAM, SUBSTATE) and np.dtype(self.dtype).kind == "f"

    def labels(self, path: str, keys: tuple[str, ...] | None = None) -> list[str]:
        """Names of the scalar elements: ``"path.name"`` or ``"path.name[i]"`` (C order).

        ``keys`` (a nested entry's key path) replaces ``name`` by ``"k0.k1…"``.
        """
        name = ".".join(keys) if keys else self.name
        base = f"{path}.{name}" if path else name
        if not self.shape:
            return [base]
        return [f"{base}[{i}]" for i in range(self.size)]


def substate(name: str, sub, description: str = "") -> StateVar:
    """The declaration of a nested state dict with entries ``sub`` (e.g. a member block's ``state_vars()``)."""
    return StateVar(name, (), SUBSTATE, "", description, batched=False, sub=tuple(sub))


def flat_state_vars(variables, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], StateVar]]:
    """Every declared entry as ``(key path, StateVar)``, nested declarations expanded (depth first)."""
    out = []
    for v in variables:
        if v.dtype == SUBSTATE:
            out += flat_state_vars(v.sub, (*prefix, v.name))
        else:
            out.append(((*prefix, v.name), v))
    return out


def state_get(state: dict, keys: tuple[str, ...]):
    """``state[k0][k1]…``."""
    for k in keys:
        state = state[k]
    return state


def state_with(state: dict, keys: tuple[str, ...], value) -> dict:
    """A copy of ``state`` with the entry at ``keys`` replaced (dicts along the path copied, nothing mutated)."""
    new = dict(state)
    new[keys[0]] = value if len(keys) == 1 else state_with(state[keys[0]], keys[1:], value)
    return new


def rng_var(description: str = "per-trial random streams, read by position") -> StateVar:
    """The declaration of a block's ``"rng"`` entry."""
    return StateVar("rng", (), STREAM, "", description, batched=False)
