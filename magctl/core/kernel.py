"""Compiled kernels of blocks: what a block gives the compiled engine, and the state layout it uses.

A block that can run compiled returns a :class:`Kernel` from ``Block.kernel()``: numba-compiled
functions of one trial over plain arrays, with the block's parameters bound at build time as
arguments (so the compiled code is cached on disk and shared by every instance). The compiled
engine (:mod:`magctl.core.compiled`) generates one step — and for ``simulate`` one loop over trials
and steps — that calls these functions in the schedule's order.

**The array convention.** Every port value and every state entry is an array ``(B, n)`` of its
dtype, ``n`` the number of elements of one trial's value (1 for a scalar), trial ``b`` in row ``b``;
a batch-wide counter is stored per trial too. A kernel
function is called for one trial ``b`` with tuples of such arrays:

* feedthrough: ``step(b, params, state, next_state, inputs, outputs, base, noise)`` writes the
  outputs and the next state together (a stateless block gets empty tuples);
* no feedthrough: ``output(b, params, state, outputs)`` (its outputs need no input), then
  ``update(b, params, state, next_state, inputs, base, noise)``.

Kernel functions allocate nothing (no ``np.empty``, no copies, no lists): the engine compiles them
without numba's reference-counted runtime, which a kernel holding many arrays would otherwise pay an
atomic count for at every use. ``params`` is the kernel's tuple of parameters; ``state`` and ``next_state`` follow
``flat_state_vars(block.state_vars())`` (random streams left out); ``inputs`` and ``outputs`` follow
the block's port order; ``noise`` is the stream key rows of a noisy kernel (an empty tuple without).

A kernel that draws noise names the state entry holding its streams (``stream="rng"``, or a dotted path
into a member's state such as ``"robot.rng"``); the engine then passes that block's stream key rows as
``noise`` (``(B, 5)`` ``uint64``, :mod:`magctl.core.philox`), and the kernel reads its numbers by
address — ``normal(noise, b, k, i)`` for draw ``i`` at the position ``k`` its state counts — exactly
the numbers the interpreted engine's :class:`~magctl.core.random.TrialStreams` gives. ``base`` is 0.

The functions below take a block (:class:`~magctl.core.block.Block`) and read its declared state
(:mod:`magctl.core.state`); this module does not import :mod:`magctl.core.block`, whose blocks run their kernels
through :mod:`magctl.core.kernel_driver`, which imports this one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from magctl.core.errors import MagctlError
from magctl.core.state import STREAM, StateVar, flat_state_vars, state_get, state_with


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
    event : str
        A bool state entry (top level, one per trial) that the kernel sets when the block needs Python at the
        end of this tick — work a kernel cannot do, such as an IPOPT plan or a path search. Both engines then
        call ``block.handle_event(state, u)`` with the next state and this tick's inputs of the flagged trials
        only (batch = their number) before the next tick; it returns their state with the flag cleared. The
        compiled loop leaves its numba code only for those trials, at those ticks, and resumes.
    stream : str
        The state entry holding the block's :class:`~magctl.core.random.TrialStreams` when its kernel draws
        noise (``"rng"``; a dotted path such as ``"robot.rng"`` names an entry of a nested state); empty
        for a kernel that draws nothing.
    in_place : bool
        The functions read every state element before writing the same element of the next
        state, so the engine may pass the state arrays as the next state too (no copy per step).
        A kernel that reads a state element after writing the next one says False.
    """

    step: Callable | None = None
    output: Callable | None = None
    update: Callable | None = None
    params: tuple = ()
    stream: str = ""
    event: str = ""
    in_place: bool = True

    def __post_init__(self):
        if (self.step is None) == (self.output is None):
            raise MagctlError("a kernel has either step (feedthrough) or output and update (no feedthrough)")
        if self.output is not None and self.update is None:
            raise MagctlError("a kernel with output needs update (give a no-op one for a stateless block)")


def compiled_vars(block) -> list[tuple[tuple[str, ...], StateVar]]:
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


def pack_state(block, state: dict, batch: int, variables=None, copy: bool = True) -> list[np.ndarray]:
    """``state`` as the kernel's arrays: one ``(B, n)`` array per entry of :func:`compiled_vars` (or of
    ``variables``, that list computed once). ``copy=False`` returns views of ``state``'s own arrays where
    their layout allows (for a kernel that only reads them)."""
    arrays = []
    for keys, var in (compiled_vars(block) if variables is None else variables):
        value = np.asarray(state_get(state, keys), dtype=var.dtype)
        if var.batched and value.shape[:1] == (batch,):
            rows = value.reshape(batch, var.size)
            # a read-only or strided array is copied: the kernels are compiled for writable C-contiguous arrays
            view = not copy and rows.flags.c_contiguous and rows.flags.writeable
            arrays.append(rows if view else rows.copy())
        else:
            rows = value.reshape(value.shape[0], -1) if var.batched else value.reshape(1, -1)
            arrays.append(np.array(np.broadcast_to(rows, (batch, var.size)), dtype=var.dtype))
    return arrays


def unpack_state(block, arrays: Sequence[np.ndarray], like: dict, variables=None) -> dict:
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


def stream_keys_of(kernel: Kernel, state: dict, batch: int) -> np.ndarray:
    """The ``(B, 5)`` stream key rows a noisy kernel reads (rows switched off when the state holds no stream:
    the noise-free path)."""
    from magctl.core.random import stream_keys

    rng = state_get(state, tuple(kernel.stream.split(".")))
    if rng is None:
        return stream_keys(0, range(batch), 0, on=False)
    if rng.batch != batch:
        raise MagctlError(f"the state's streams hold {rng.batch} trials, not {batch}")
    return rng.keys


def event_index(block, kernel: Kernel, variables=None) -> int:
    """Position of the kernel's event flag among :func:`compiled_vars` (``-1`` without an event)."""
    if not kernel.event:
        return -1
    for v, (keys, var) in enumerate(compiled_vars(block) if variables is None else variables):
        if keys == (kernel.event,):
            if var.dtype != "bool" or not var.batched or var.shape:
                raise MagctlError(f"block {block.name!r}: event flag {kernel.event!r} must be a per-trial bool")
            return v
    raise MagctlError(f"block {block.name!r}: its kernel's event flag {kernel.event!r} is not a state entry")


def handle_events(block, arrays: Sequence[np.ndarray], inputs: dict, rows: np.ndarray, like: dict,
                  flag: int, variables=None) -> None:
    """Run ``block.handle_event`` for the trials ``rows`` of the kernel state ``arrays`` (``(B, n)`` each,
    updated in place) with their inputs ``inputs`` (already the rows' values); ``like`` supplies the state
    entries a kernel does not hold (streams)."""
    variables = compiled_vars(block) if variables is None else variables
    sub = unpack_state(block, [a[rows] for a in arrays], like, variables)
    new = block.handle_event(sub, inputs)
    packed = pack_state(block, new, len(rows), variables)
    if packed[flag].any():
        raise MagctlError(f"block {block.name!r}: handle_event left its event flag set")
    for arr, value in zip(arrays, packed, strict=True):
        arr[rows] = value


@dataclass
class EventRequest:
    """A Python event taken off the tick that raised it (:attr:`Kernel.event`; docs/core.md "Python events").

    A stepper whose ``defer`` hook is set (:class:`~magctl.core.compiled.Stepper`,
    :class:`~magctl.core.kernel_driver.KernelDriver`) does not call ``handle_event`` at the end of the tick:
    it hands the hook what the call needs — the flagged trials' state after that tick and their inputs in it,
    both copies — and leaves the flag up, so the event is pending and the kernel sees its flag at the start of
    the next ticks. :meth:`run` (any thread) gives the handler's result; the stepper's ``apply_event`` merges it
    (:func:`merge_event`) when the caller decides.

    Attributes
    ----------
    block : Block
        The block (a :class:`~magctl.core.block.Block`) whose kernel raised the flag.
    rows : ndarray of int
        The flagged trials (batch rows).
    state, inputs : dict
        Their state after the tick that raised the flag and their inputs in that tick (the rows only).
    tick : int
        The tick that raised the flag: the compiled stepper's count of steps before it (the first step is 0); the
        kernel driver, which counts no steps, leaves it to its caller (the rig's controller sets its own count).
    """

    block: object
    rows: np.ndarray
    state: dict
    inputs: dict
    tick: int = 0

    def run(self) -> dict:
        """``block.handle_event(state, inputs)``: the rows' state with the flag cleared."""
        return self.block.handle_event(self.state, self.inputs)


def merge_event(block, arrays: Sequence[np.ndarray], rows: np.ndarray, before: dict, after: dict, flag: int,
                variables=None) -> None:
    """Write an event's result into the kernel state ``arrays`` (``(B, n)`` each, updated in place) at the
    trials ``rows``, ticks after the one that raised the flag: every element the handler changed (``after``
    against ``before``, the state it was given) takes the handler's value; every other element keeps the value
    the ticks in between gave it. Applied at once (no tick in between), this is what :func:`handle_events`
    writes."""
    variables = compiled_vars(block) if variables is None else variables
    old = pack_state(block, before, len(rows), variables)
    new = pack_state(block, after, len(rows), variables)
    if new[flag].any():
        raise MagctlError(f"block {block.name!r}: handle_event left its event flag set")
    for arr, o, n in zip(arrays, old, new, strict=True):
        changed = o != n
        if n.dtype.kind == "f":
            changed &= ~(np.isnan(o) & np.isnan(n))
        if changed.any():
            current = arr[rows]
            current[changed] = n[changed]
            arr[rows] = current
