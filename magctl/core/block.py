"""The block: declared ports, declared state, a sample period, and behaviour without state.

A block never stores the state of a run. ``initial_state`` makes it,
``output(state, u)`` reads it and never writes it, ``update(state, u)``
returns the next one and never mutates its argument, so a diagram can
evaluate every output in feedthrough order before advancing any state, and
the same block instance can run a 10 000-trial batch and a one-trial rig loop
at once.

A value a block needs in both its output and its next state (a control law,
a filter's posterior) is not stashed in the state: the engine calls
``step(state, u) -> (outputs, next_state)`` once per tick for feedthrough
blocks, whose inputs are all known when their outputs are due, and such
blocks override ``step`` to compute the value once (Drake's per-step cache
entries play this role there). A block without feedthrough has no inputs when
its outputs are due; anything its outputs need is state, computed by the
previous ``update``.

State is a ``dict`` whose entries the block declares with :class:`StateVar`
(:meth:`Block.state_vars`; the declarations are :mod:`magctl.core.state`'s): arrays with a leading trial axis, a few
batch-wide counters, and, for blocks that draw noise, a ``TrialStreams``
read by position (:mod:`magctl.core.random`).
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping, Sequence

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.errors import NotLinearError, WiringError
from magctl.core.ports import Port
from magctl.core.random import TrialStreams
from magctl.core.state import (  # noqa: F401 (the state declarations, re-exported: blocks import them from here)
    STREAM,
    SUBSTATE,
    State,
    StateVar,
    flat_state_vars,
    rng_var,
    state_get,
    state_with,
    substate,
)

Signals = Mapping[str, np.ndarray]

_DRIVERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""Each kernelled block's :class:`~magctl.core.kernel_driver.KernelDriver` (None for a Python block)."""


class Block:
    """Base class of every magctl block.

    Parameters
    ----------
    name : str
        Name, unique within the diagram that holds the block.
    inputs, outputs : sequence of Port
        Declared ports; arrays on them are shaped ``(B, *port.shape)``.
    dt : float
        Sample period in seconds; a multiple of the diagram's base period
        (the 30 Hz frame period by default).
    feedthrough : bool
        True when some output depends on the current input, so the block's
        outputs must be computed after its inputs' producers.

    Notes
    -----
    Subclasses override :meth:`state_vars`, :meth:`initial_state`,
    :meth:`output` and :meth:`update` (and :meth:`step` when output and
    update share work); linear ones also :meth:`to_control`.
    """

    def __init__(
        self,
        name: str,
        *,
        inputs: Sequence[Port] = (),
        outputs: Sequence[Port] = (),
        dt: float = FRAME_PERIOD_S,
        feedthrough: bool = True,
    ):
        if not name or "." in name or "/" in name:
            raise WiringError(f"block name {name!r} must be non-empty and contain no '.' or '/'")
        self.name = name
        self.inputs: dict[str, Port] = _port_table(name, "input", inputs)
        self.outputs: dict[str, Port] = _port_table(name, "output", outputs)
        if dt <= 0 or not np.isfinite(dt):
            raise WiringError(f"block {name!r}: sample period dt={dt!r} must be positive")
        self.dt = float(dt)
        self.feedthrough = bool(feedthrough)

    # --- behaviour -----------------------------------------------------------------------
    def state_vars(self) -> tuple[StateVar, ...]:
        """The entries of this block's state (none for a stateless block)."""
        return ()

    def initial_state(self, batch: int, rng: TrialStreams | None = None) -> State:
        """State of ``batch`` trials at step 0; ``rng`` holds the block's per-trial streams."""
        return {}

    def output(self, state: State, u: Signals) -> dict[str, np.ndarray]:
        """Outputs at the current step from the state and (if feedthrough) the inputs; reads ``state`` only.

        A block with a kernel gets this from its kernel (:mod:`magctl.core.kernel_driver`)."""
        driver = self.kernel_driver()
        if driver is None:
            raise NotImplementedError(f"{type(self).__name__} must define output() or kernel()")
        return driver.step(state, u)[0] if self.feedthrough else driver.output(state)

    def update(self, state: State, u: Signals) -> State:
        """State at the next step, a new dict (``state`` is not modified). Stateless blocks return ``state``.

        A block with a kernel gets this from its kernel."""
        driver = self.kernel_driver()
        if driver is None:
            return state
        return driver.step(state, u)[1] if self.feedthrough else driver.update(state, u)

    def step(self, state: State, u: Signals) -> tuple[dict[str, np.ndarray], State]:
        """Outputs now and the next state, equal to ``(output(state, u), update(state, u))``.

        The engine calls this once per tick for feedthrough blocks: a block with a kernel runs its step
        kernel once; a Python block overrides it to compute what output and update share only once.
        """
        driver = self.kernel_driver()
        if driver is not None and self.feedthrough:
            return driver.step(state, u)
        return self.output(state, u), self.update(state, u)

    def kernel(self):
        """The block's behaviour as a per-trial kernel (:class:`magctl.core.kernel.Kernel`), or None for a
        Python block. Both engines run it: the compiled one fused into one loop, the interpreted one through
        :meth:`kernel_driver`."""
        return None

    def handle_event(self, state: State, u: Signals) -> State:
        """The Python part of a kernelled block, for the trials whose kernel raised its event flag
        (``Kernel.event``): ``state`` and ``u`` hold those trials only; returns their state with the flag
        cleared. Called by both engines at the end of the tick in which the flag was raised."""
        raise NotImplementedError(f"{type(self).__name__}'s kernel raises an event but the block handles none")

    def kernel_driver(self):
        """The driver running :meth:`kernel` over a batch (built on first use, kept beside the block rather than
        in it, so that a block's attributes stay its parameters), or None for a Python block."""
        try:
            return _DRIVERS[self]
        except KeyError:
            pass
        kernel = self.kernel()
        if kernel is None:
            driver = None
        else:
            from magctl.core.kernel_driver import KernelDriver

            driver = KernelDriver(self, kernel)
        _DRIVERS[self] = driver
        return driver

    # --- analysis hooks ------------------------------------------------------------------
    def to_control(self):
        """The block as a python-control system with ``dt``; linear blocks only."""
        raise NotLinearError(f"block {self.name!r} ({type(self).__name__}) is not linear")

    @property
    def uses_random(self) -> bool:
        """True if the block draws noise and wants per-trial streams."""
        return False

    # --- helpers -------------------------------------------------------------------------
    def input_port(self, name: str) -> Port:
        try:
            return self.inputs[name]
        except KeyError:
            raise WiringError(
                f"block {self.name!r} has no input {name!r}; inputs: {sorted(self.inputs) or 'none'}"
            ) from None

    def output_port(self, name: str) -> Port:
        try:
            return self.outputs[name]
        except KeyError:
            raise WiringError(
                f"block {self.name!r} has no output {name!r}; outputs: {sorted(self.outputs) or 'none'}"
            ) from None

    def __repr__(self) -> str:
        ins = ", ".join(p.describe() for p in self.inputs.values())
        outs = ", ".join(p.describe() for p in self.outputs.values())
        return f"<{type(self).__name__} {self.name!r} ({ins}) -> ({outs}) dt={self.dt:.6g}s>"


def _port_table(block: str, kind: str, ports: Sequence[Port]) -> dict[str, Port]:
    table: dict[str, Port] = {}
    for p in ports:
        if not isinstance(p, Port):
            raise WiringError(f"block {block!r}: {kind} {p!r} is not a Port")
        if p.name in table:
            raise WiringError(f"block {block!r} declares {kind} {p.name!r} twice")
        table[p.name] = p
    return table


def as_batch(value, port: Port, batch: int) -> np.ndarray:
    """Broadcast a constant or per-trial value to ``(batch, *port.shape)``."""
    arr = np.asarray(value, dtype=port.dtype)
    try:
        return np.broadcast_to(arr, (batch, *port.shape)).copy()
    except ValueError:
        raise WiringError(
            f"value of shape {arr.shape} does not fit port {port.describe()} with batch {batch}"
        ) from None
