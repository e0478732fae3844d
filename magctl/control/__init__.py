"""Controller blocks: tracker, visual servo, path planner, push tasks."""

from magctl.control.learning import LearningLaw, front_push_law, side_push_law
from magctl.control.planner import Planner, PlanningError, plan_path
from magctl.control.push import AssemblyTask, FrontAssemblyTask, FrontPushTask, SidePushTask
from magctl.control.servo import Servo, servo_params
from magctl.sensing.tracker import Tracker

__all__ = ["Planner", "PlanningError", "Servo", "Tracker", "plan_path", "servo_params"]
__all__ += ["AssemblyTask", "FrontAssemblyTask", "FrontPushTask", "LearningLaw", "SidePushTask", "front_push_law",
            "side_push_law"]
