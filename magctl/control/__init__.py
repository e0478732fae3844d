"""Controller blocks: visual servo, learning laws, path planner, push tasks, status codes."""

from magctl.control.learning import LearningLaw, front_push_law, side_push_law
from magctl.control.planner import Planner, PlanningError, plan_path
from magctl.control.push import AssemblyTask, FrontAssemblyTask, FrontPushTask, SidePushTask
from magctl.control.servo import Servo, servo_params
from magctl.control.status import Status

__all__ = ["AssemblyTask", "FrontAssemblyTask", "FrontPushTask", "LearningLaw", "Planner", "PlanningError", "Servo",
           "SidePushTask", "Status", "front_push_law", "plan_path", "servo_params", "side_push_law"]
