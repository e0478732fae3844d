"""The block model: ports, blocks, diagrams, batched simulation, python-control export."""

from magctl.core.block import Block, StateVar, as_batch
from magctl.core.diagram import Diagram
from magctl.core.errors import (
    AlgebraicLoopError,
    MagctlError,
    NonFiniteSignalError,
    NotLinearError,
    ParameterError,
    RateError,
    WiringError,
)
from magctl.core.linear import PI, Constant, Delay, Gain, Integrator, StateSpace, Sum
from magctl.core.nonlinear import GaussianNoise, NormSaturation, clip_norm
from magctl.core.ports import Port, port
from magctl.core.random import TrialStreams, trial_seed_sequence
from magctl.core.simulate import SimResult, simulate

__all__ = [
    "PI", "AlgebraicLoopError", "Block", "Constant", "Delay", "Diagram", "Gain", "GaussianNoise", "Integrator",
    "MagctlError", "NonFiniteSignalError", "NormSaturation", "NotLinearError", "ParameterError", "Port",
    "RateError", "SimResult", "StateSpace", "StateVar", "Sum", "TrialStreams", "WiringError", "as_batch", "clip_norm",
    "port", "simulate", "trial_seed_sequence",
]
