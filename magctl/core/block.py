"""The block: declared ports, a sample period, and behaviour without state.

A block never stores the state of a run. ``initial_state`` makes it,
``output(state, u)`` reads it, ``update(state, u)`` returns the next one, so a
diagram can evaluate every output in feedthrough order before advancing any
state, and the same block instance can run a 10 000-trial batch and a
one-trial rig loop at once.

State is a ``dict`` of arrays with a leading trial axis (plus, for blocks that
draw noise, a ``TrialStreams`` under the key ``"rng"``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from magctl import FRAME_PERIOD_S
from magctl.core.errors import NotLinearError, WiringError
from magctl.core.ports import Port
from magctl.core.random import TrialStreams

State = dict
Signals = Mapping[str, np.ndarray]


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

    Subclasses override :meth:`initial_state`, :meth:`output` and
    :meth:`update`; linear ones also :meth:`to_control`.
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
    def initial_state(self, batch: int, rng: TrialStreams | None = None) -> State:
        """State of ``batch`` trials at step 0; ``rng`` holds the block's per-trial streams."""
        return {}

    def output(self, state: State, u: Signals) -> dict[str, np.ndarray]:
        """Outputs at the current step from the state and (if feedthrough) the inputs."""
        raise NotImplementedError(f"{type(self).__name__} must define output()")

    def update(self, state: State, u: Signals) -> State:
        """State at the next step. Stateless blocks return ``state`` unchanged."""
        return state

    def step(self, state: State, u: Signals) -> tuple[dict[str, np.ndarray], State]:
        """Outputs now and the next state: ``output`` then ``update``."""
        return self.output(state, u), self.update(state, u)

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
