"""The block model: ports, blocks, diagrams, batched simulation, python-control export.

Names are imported on first use (PEP 562), so ``import magctl.core.errors`` — what the command
line needs to start — does not pull in python-control or scipy.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "Block": "block", "StateVar": "block", "as_batch": "block",
    "Diagram": "diagram",
    "AlgebraicLoopError": "errors", "MagctlError": "errors", "NonFiniteSignalError": "errors",
    "NotLinearError": "errors", "ParameterError": "errors", "RateError": "errors", "WiringError": "errors",
    "PI": "linear", "Constant": "linear", "Delay": "linear", "Gain": "linear", "Integrator": "linear",
    "StateSpace": "linear", "Sum": "linear",
    "GaussianNoise": "nonlinear", "NormSaturation": "nonlinear",
    "Port": "ports", "port": "ports",
    "TrialStreams": "random", "trial_seed_sequence": "random",
    "SimResult": "simulation", "simulate": "simulation",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    try:
        module = _WHERE[name]
    except KeyError:
        raise AttributeError(f"module 'magctl.core' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f"magctl.core.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
