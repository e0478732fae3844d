"""Push tasks (§V): front pushing, side pushing and two-sphere assembly.

Each task is a block at the camera rate with inputs ``robot_est`` (2,) m,
``spheres_est`` (N, 2) m, ``lost`` () and outputs ``target`` (2,) m, ``speed_cap``
() m/s, ``status`` (), ``attempt`` (), ``phase`` () and ``correction`` () m — see
``docs/interfaces.md`` and ``docs/push-control.md``. Status codes are
:class:`magctl.control.status.Status`.
"""

from magctl.control.push.assembly import AssemblyTask, FrontAssemblyTask
from magctl.control.push.front import FrontPushTask
from magctl.control.push.side import SidePushTask

__all__ = ["AssemblyTask", "FrontAssemblyTask", "FrontPushTask", "SidePushTask"]
