"""Fluid physics of the pushing rig: surface forces, near-wall drag, the robot's Stokes flow.

Plain functions the controllers use (lengths in metres):

* :func:`sidepush_curve`, :func:`sidepush_fit`, :func:`gap_for_displacement` — Fig 6 and eq 22;
* :func:`contact_threshold` — the side gap below which the robot touches the sphere;
* :func:`release_displacement` — D_p,r, the front-push compensation δ(0) (eq 10);
* :func:`pull_off_range` — eq 1-3.
"""

from magctl.plant.fluid.flow import RobotFlow, clear_cache, robot_flow
from magctl.plant.fluid.geometry import RobotGeometry
from magctl.plant.fluid.scenarios import (
    SidePushResult,
    contact_threshold,
    gap_for_displacement,
    release_displacement,
    sidepush_curve,
    sidepush_fit,
)
from magctl.plant.fluid.surface import jkr_pull_off, pull_off_range, work_of_adhesion

__all__ = [
    "RobotFlow", "RobotGeometry", "SidePushResult", "clear_cache", "contact_threshold", "gap_for_displacement",
    "jkr_pull_off", "pull_off_range", "release_displacement", "robot_flow", "sidepush_curve", "sidepush_fit",
    "work_of_adhesion",
]
