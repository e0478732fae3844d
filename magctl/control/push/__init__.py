"""Push tasks (§V): front pushing, side pushing and two-sphere assembly, with status codes.

Each task is a block at the camera rate with inputs ``robot_est`` (2,) m,
``spheres_est`` (N, 2) m, ``lost`` () and outputs ``target`` (2,) m, ``speed_cap``
() m/s, ``status`` (), ``attempt`` (), ``phase`` () and ``correction`` () m — see
``docs/interfaces.md`` and ``docs/push-control.md``.
"""

from magctl.control.push.assembly import AssemblyTask, FrontAssemblyTask
from magctl.control.push.common import (
    ATTEMPT_LIMIT,
    CONVERGED,
    RUNNING,
    SPHERE_LOST,
    STALLED,
    STATUS_NAMES,
    TRACKING_LOST,
    ExpSideModel,
    LinSideModel,
    side_model,
)
from magctl.control.push.front import FrontPushTask
from magctl.control.push.side import SidePushTask

__all__ = [
    "ATTEMPT_LIMIT", "CONVERGED", "RUNNING", "SPHERE_LOST", "STALLED", "STATUS_NAMES", "TRACKING_LOST",
    "AssemblyTask", "ExpSideModel", "FrontAssemblyTask", "FrontPushTask", "LinSideModel", "SidePushTask",
    "side_model",
]
