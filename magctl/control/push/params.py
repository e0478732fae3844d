"""The push tasks' parameter records, under their former name: they live in :mod:`magctl.control.push_params`, below
the tasks, so the blocks the tasks use (the assembly planners) read them without importing the tasks.

Only :mod:`magctl.control.push.planned` still imports this name; import :mod:`magctl.control.push_params`.
"""

from magctl.control.push_params import (
    AssemblyParams,
    CommonParams,
    DirtParams,
    FrontParams,
    PlannedParams,
    PushParams,
    SideParams,
)

__all__ = ["AssemblyParams", "CommonParams", "DirtParams", "FrontParams", "PlannedParams", "PushParams", "SideParams"]
