"""Exceptions raised by the block model; each names the block and port at fault."""


class MagctlError(Exception):
    """Base class of every error magctl raises on purpose."""


class WiringError(MagctlError):
    """A diagram is miswired: unknown port, unconnected input, two drivers, shape or unit mismatch."""


class AlgebraicLoopError(WiringError):
    """Feedthrough blocks form a cycle; ``cycle`` lists the blocks in order."""

    def __init__(self, cycle: list[str]):
        self.cycle = list(cycle)
        path = " -> ".join([*self.cycle, self.cycle[0]])
        super().__init__(f"algebraic loop through feedthrough blocks: {path}")


class RateError(WiringError):
    """A block's period is not an integer multiple of the diagram's base period."""


class NonFiniteSignalError(MagctlError):
    """A NaN or infinity appeared on a signal during simulation.

    Attributes
    ----------
    step : int
        Tick at which the value first appeared.
    source : str
        ``block.port`` that produced it.
    consumers : list of str
        ``block.port`` inputs it enters.
    partial : SimResult or None
        Everything simulated before the fault.
    """

    def __init__(self, step: int, source: str, consumers: list[str], trials: list[int], partial=None):
        self.step, self.source, self.consumers, self.trials = step, source, list(consumers), list(trials)
        self.partial = partial
        into = ", ".join(consumers) if consumers else "no block (diagram output)"
        shown = ", ".join(map(str, trials[:5])) + (" …" if len(trials) > 5 else "")
        super().__init__(f"non-finite value on {source} at step {step} (trials {shown}), entering {into}")


class NotLinearError(MagctlError):
    """A block was asked for a python-control model but is not linear."""


class ParameterError(MagctlError):
    """A parameter file is malformed; the message names the file and the key."""
