"""Controller blocks: tracker, visual servo, path planner, push tasks."""

from magctl.control.planner import Planner, PlanningError, plan_path
from magctl.control.servo import Servo, servo_params
from magctl.control.tracker import Tracker

__all__ = ["Planner", "PlanningError", "Servo", "Tracker", "plan_path", "servo_params"]
