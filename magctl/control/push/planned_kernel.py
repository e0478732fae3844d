"""The compiled frame of :class:`~magctl.control.push.planned.PlannedAssemblyTask`: the planned assembly's step
(:func:`~magctl.control.push.kernels.planned_step`) behind the hold that keeps the robot still while a plan is
awaited (docs/rig.md "Planning off the frame"). Its numpy reference is ``tests/reference/planned_blocks.py`` (the
hold never runs there: a study handles the plan at the end of the frame that asks for it, and with the default
``plan_frames`` = 1 waits no frame) and, for the hold, ``tests/rig/test_planning_off_frame.py``.
"""

from __future__ import annotations

import math

from magctl.control.push.kernels import RUNNING, copy_planned_state, jit, planned_step, write_outputs


@jit
def planned_frame(b, params, state, next_state, inputs, outputs, base, noise):
    """The planned assembly's frame: :func:`~magctl.control.push.kernels.planned_step`, except while a plan is
    awaited — its ``plan_due`` flag still up at the start of the frame (a rig planning off the tick) or the
    ``plan_frames`` wait not over. Then the frame holds the robot: the state as it is (the wait counted down), speed
    cap 0, the target kept (the robot where it is before the first pass). Raising ``plan_due`` starts the wait."""
    robot = inputs[0]
    due = state[21]
    wait = state[22]
    w = wait[b, 0]
    if state[1][b, 0] == RUNNING and (due[b, 0] or w > 0):
        copy_planned_state(b, state[0:22], next_state[0:22])
        next_state[22][b, 0] = w - 1 if w > 0 else 0
        target = state[5]
        t0 = target[b, 0]
        t1 = target[b, 1]
        e = state[11][b, 0]
        write_outputs(b, outputs, (robot[b, 0] if math.isnan(t0) else t0, robot[b, 1] if math.isnan(t1) else t1,
                                   0.0, state[1][b, 0], state[2][b, 0], state[0][b, 0], 0.0 if math.isnan(e) else e))
        g = state[20][b, 0]
        outputs[6][b, 0] = 0.0 if math.isnan(g) else g
        return
    planned_step(b, params[0:6], state[0:22], next_state[0:22], inputs, outputs, base, noise)
    next_state[22][b, 0] = params[6] - 1 if next_state[21][b, 0] else 0
