"""Compiled kernels of blocks: what a block gives the compiled engine, and the state layout it uses.

A block that can run compiled returns a :class:`Kernel` from ``Block.kernel()``: numba-compiled
functions of one trial over plain arrays, with the block's parameters bound at build time as
arguments (so the compiled code is cached on disk and shared by every instance). The compiled
engine (:mod:`magctl.core.compiled`) generates one step — and for ``simulate`` one loop over trials
and steps — that calls these functions in the schedule's order.

**The array convention.** Every port value and every state entry is an array ``(B, n)`` of its
dtype, ``n`` the number of elements of one trial's value (1 for a scalar), trial ``b`` in row ``b``;
a batch-wide counter is stored per trial too. Noise arrays are ``(B, steps, n)``. A kernel
function is called for one trial ``b`` with tuples of such arrays:

* feedthrough: ``step(b, params, state, next_state, inputs, outputs, base, noise)`` writes the
  outputs and the next state together (a stateless block gets empty tuples);
* no feedthrough: ``output(b, params, state, outputs)`` (its outputs need no input), then
  ``update(b, params, state, next_state, inputs, base, noise)``.

Kernel functions allocate nothing (no ``np.empty``, no copies, no lists): the engine compiles them
without numba's reference-counted runtime, which a kernel holding many arrays would otherwise pay an
atomic count for at every use. ``params`` is the kernel's tuple of parameters; ``state`` and ``next_state`` follow
``flat_state_vars(block.state_vars())`` (random streams left out); ``inputs`` and ``outputs`` follow
the block's port order; ``noise`` holds one array per declared draw (an empty tuple without).

A kernel that draws noise declares it with ``noise``: the ``(kind, shape)`` draws of the block's
stream in the order the block makes them at each position, and the name of the state entry that
counts positions. The engine draws them beforehand from the same per-trial streams
(:func:`stream_draws`), so a trial's numbers are those of the interpreted engine; the kernel reads
position ``p`` at ``noise[b, p - base]``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from magctl.core.block import STREAM, Block, StateVar, flat_state_vars, state_get, state_with
from magctl.core.errors import MagctlError
from magctl.core.random import TrialStreams


@dataclass(frozen=True)
class Kernel:
    """A block's compiled form (see the module docstring for the calling convention).

    Attributes
    ----------
    step : numba dispatcher, optional
        Outputs and next state of one trial (feedthrough blocks).
    output, update : numba dispatcher, optional
        Outputs from the state, then the next state (blocks without feedthrough).
    params : tuple
        The functions' ``params``: floats, ints, bools and contiguous arrays.
    noise : tuple of (str, tuple)
        ``(kind, shape)`` of each noise draw per position, in the order the block draws them
        (kinds of :class:`~magctl.core.random.TrialStreams`: ``"standard_normal"``, ``"random"``).
    position : str
        State entry holding the stream position of the next draw (with ``noise``); a dotted path
        (``"robot.k"``) names an entry of a nested state, whose ``"rng"`` entry is then the stream.
    in_place : bool
        The functions read every state element before writing the same element of the next
        state, so the engine may pass the state arrays as the next state too (no copy per step).
        A kernel that reads a state element after writing the next one says False.
    """

    step: Callable | None = None
    output: Callable | None = None
    update: Callable | None = None
    params: tuple = ()
    noise: tuple = field(default_factory=tuple)
    position: str = ""
    in_place: bool = True

    def __post_init__(self):
        if (self.step is None) == (self.output is None):
            raise MagctlError("a kernel has either step (feedthrough) or output and update (no feedthrough)")
        if self.output is not None and self.update is None:
            raise MagctlError("a kernel with output needs update (give a no-op one for a stateless block)")
        if self.noise and not self.position:
            raise MagctlError("a kernel that draws noise names the state entry counting its position")


def compiled_vars(block: Block) -> list[tuple[tuple[str, ...], StateVar]]:
    """The state entries a kernel sees: every declared entry except random streams, in declaration order."""
    out = []
    for keys, var in flat_state_vars(block.state_vars()):
        if var.dtype == STREAM:
            continue
        if var.dtype == "object":
            raise MagctlError(f"block {block.name!r}: state entry {'.'.join(keys)!r} is an object, which a "
                              "kernel cannot hold")
        out.append((keys, var))
    return out


def pack_state(block: Block, state: dict, batch: int, variables=None) -> list[np.ndarray]:
    """``state`` as the kernel's arrays: one ``(B, n)`` array per entry of :func:`compiled_vars` (or of
    ``variables``, that list computed once)."""
    arrays = []
    for keys, var in (compiled_vars(block) if variables is None else variables):
        value = np.asarray(state_get(state, keys), dtype=var.dtype)
        rows = value.reshape(value.shape[0], -1) if var.batched else value.reshape(1, -1)
        arrays.append(np.array(np.broadcast_to(rows, (batch, var.size)), dtype=var.dtype))
    return arrays


def unpack_state(block: Block, arrays: Sequence[np.ndarray], like: dict, variables=None) -> dict:
    """The kernel's arrays back into a state dict shaped as ``like`` (streams and the rest kept from it)."""
    state = like
    for (keys, var), arr in zip(compiled_vars(block) if variables is None else variables, arrays, strict=True):
        if var.batched:
            value = arr.reshape((arr.shape[0], *var.shape)).copy()
        else:
            value = arr[0].reshape(var.shape).copy()
            if not var.shape:
                value = value.item()
        state = state_with(state, keys, value)
    return state


def port_width(port) -> int:
    """Elements of one trial's value on ``port`` (1 for a scalar)."""
    return int(np.prod(port.shape, dtype=int))


def stream_draws(rng: TrialStreams, draws: Sequence[tuple[str, tuple]], start: int, count: int) -> list[np.ndarray]:
    """Positions ``start … start+count−1`` of a block's stream, one ``(B, count, n)`` array per draw.

    The interpreted engine refills each ``(kind, shape)`` in chunks of ``rng.chunk`` positions from the
    trial's one generator, in the order the block first asks for them, starting at position 0; this
    repeats those refills from the trial's seed sequence, so the numbers are the same. It assumes what
    every random block does: all of its draws are asked for at every position, in ``draws``' order.
    """
    if rng.sequences is None:
        raise MagctlError("compiled noise needs streams made from seed sequences")
    chunk = rng.chunk
    n_chunks = (start + count + chunk - 1) // chunk
    out = [np.empty((rng.batch, n_chunks * chunk, max(int(np.prod(shape, dtype=int)), 1))) for _, shape in draws]
    for b, seq in enumerate(rng.sequences):
        gen = np.random.default_rng(seq)
        if len(draws) == 1:  # one kind: its chunks are consecutive draws
            kind, shape = draws[0]
            out[0][b] = getattr(np.random.Generator, kind)(gen, (n_chunks * chunk, *shape)).reshape(
                n_chunks * chunk, -1)
            continue
        for c in range(n_chunks):
            for (kind, shape), arr in zip(draws, out, strict=True):
                block = getattr(np.random.Generator, kind)(gen, (chunk, *shape))
                arr[b, c * chunk:(c + 1) * chunk] = block.reshape(chunk, -1)
    return [np.ascontiguousarray(arr[:, start:start + count]) for arr in out]
