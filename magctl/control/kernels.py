"""Compiled kernels of the controller blocks: the PI servo, the learning law, the go-to status and the patrol.

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy form (``np.minimum``/``np.maximum``
propagate NaN, as :func:`nan_min` / :func:`nan_max` do here). The push tasks' kernels are in
:mod:`magctl.control.push.kernels`. Imported only when a diagram is compiled, so that numba stays out
of the import of ``magctl``.
"""

from __future__ import annotations

import math

import numba

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")

RUNNING, CONVERGED, TRACKING_LOST = 0, 1, 3
"""Status codes (:class:`magctl.control.status.Status`)."""


@jit
def nan_min(a, b):
    """``np.minimum(a, b)`` of two floats: NaN if either is NaN."""
    if a != a or a <= b:
        return a
    return b


@jit
def nan_max(a, b):
    """``np.maximum(a, b)`` of two floats: NaN if either is NaN."""
    if a != a or a >= b:
        return a
    return b


# --- PI servo (Servo.step) ----------------------------------------------------------------------------
@jit
def _servo(b, params, state, next_state, target, robot, cap_in, has_cap, hold, outputs):
    """:meth:`magctl.control.servo.Servo.step`: ``u = Kp·e + Ki·I``, speed ``min(‖u‖, v_cap)`` (or ``v_cap`` with
    ``constant_speed``), heading ``atan2(u_y, u_x)``, ``I += T·e`` unless arrived, held or (anti-windup) saturated;
    without anti-windup ``Ki·‖I‖`` clamped at ``v_cap``."""
    kp, ki, speed_max, arrive_tol, anti_windup, constant_speed, dt = params
    integral, heading = state
    n_integral, n_heading = next_state
    speed_o, heading_o, arrived_o, sat_o = outputs
    e0 = target[b, 0] - robot[b, 0]
    e1 = target[b, 1] - robot[b, 1]
    ok = math.isfinite(e0) and math.isfinite(e1) and not hold
    if not ok:
        e0 = 0.0
        e1 = 0.0
    dist = math.sqrt(e0 * e0 + e1 * e1)
    arrived = ok and dist < arrive_tol
    cap = speed_max
    if has_cap:
        cap = nan_min(speed_max, nan_max(cap_in, 0.0))
    i0 = integral[b, 0]
    i1 = integral[b, 1]
    raw0 = kp * e0 + ki * i0
    raw1 = kp * e1 + ki * i1
    mag = math.sqrt(raw0 * raw0 + raw1 * raw1)
    sat = mag > cap
    speed = nan_min(mag, cap)
    if constant_speed:
        speed = cap
        sat = mag > 0
    moving = ok and not arrived
    if not moving:
        speed = 0.0
    head = math.atan2(raw1, raw0) if mag > 0 else heading[b, 0]
    speed_o[b, 0] = speed
    heading_o[b, 0] = head
    arrived_o[b, 0] = arrived
    sat_o[b, 0] = sat and moving
    integrate = ok and not arrived
    if anti_windup:
        integrate = integrate and not (sat and moving)
    w = 1.0 if integrate else 0.0
    i0 = i0 + (dt * e0) * w
    i1 = i1 + (dt * e1) * w
    if not anti_windup and ki > 0:
        m = ki * math.sqrt(i0 * i0 + i1 * i1)
        scale = cap / (m if m > 0 else 1.0) if m > cap else 1.0
        i0 = i0 * scale
        i1 = i1 * scale
    n_integral[b, 0] = i0
    n_integral[b, 1] = i1
    n_heading[b, 0] = head


@jit
def servo_step(b, params, state, next_state, inputs, outputs, base, noise):
    """Servo with inputs ``target``, ``robot_est``."""
    target, robot = inputs
    _servo(b, params, state, next_state, target, robot, 0.0, False, False, outputs)


@jit
def servo_cap_step(b, params, state, next_state, inputs, outputs, base, noise):
    """Servo with inputs ``target``, ``robot_est``, ``speed_cap``."""
    target, robot, cap = inputs
    _servo(b, params, state, next_state, target, robot, cap[b, 0], True, False, outputs)


@jit
def servo_hold_step(b, params, state, next_state, inputs, outputs, base, noise):
    """Servo with inputs ``target``, ``robot_est``, ``hold``."""
    target, robot, hold = inputs
    _servo(b, params, state, next_state, target, robot, 0.0, False, hold[b, 0], outputs)


@jit
def servo_cap_hold_step(b, params, state, next_state, inputs, outputs, base, noise):
    """Servo with inputs ``target``, ``robot_est``, ``speed_cap``, ``hold``."""
    target, robot, cap, hold = inputs
    _servo(b, params, state, next_state, target, robot, cap[b, 0], True, hold[b, 0], outputs)


# --- learning law (eq 13, eq 18) ----------------------------------------------------------------------
@jit
def law_gain(gain, b):
    """The law's gain of trial ``b``: one for every trial (length 1) or one per trial."""
    return gain[b] if gain.shape[0] > 1 else gain[0]


@jit
def law_output(b, params, state, outputs):
    """:class:`magctl.control.learning.LearningLaw`: ``y(i) = x(i)``."""
    x, = state
    y, = outputs
    y[b, 0] = x[b, 0]


@jit
def law_update(b, params, state, next_state, inputs, base, noise):
    """:class:`magctl.control.learning.LearningLaw`: ``x(i+1) = x(i) + g·e(i)`` (eq 13, eq 18)."""
    gain, = params
    x, = state
    nx, = next_state
    e, = inputs
    nx[b, 0] = x[b, 0] + law_gain(gain, b) * e[b, 0]


# --- go-to status and patrol (guards.py) ----------------------------------------------------------------
@jit
def arrival_status_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`magctl.control.guards.ArrivalStatus`: TRACKING_LOST while lost, else CONVERGED once arrived."""
    arrived, lost = inputs
    status, = outputs
    status[b, 0] = TRACKING_LOST if lost[b, 0] else (CONVERGED if arrived[b, 0] else RUNNING)


@jit
def patrol_output(b, params, state, outputs):
    """:class:`magctl.control.guards.Patrol`: the current waypoint, RUNNING, laps so far."""
    waypoints, tol = params
    i, lap = state
    target, status, lap_o = outputs
    k = i[b, 0]
    target[b, 0] = waypoints[k, 0]
    target[b, 1] = waypoints[k, 1]
    status[b, 0] = RUNNING
    lap_o[b, 0] = lap[b, 0]


@jit
def patrol_update(b, params, state, next_state, inputs, base, noise):
    """:class:`magctl.control.guards.Patrol`: within ``tol`` of the waypoint, move on to the next (a lap at 0)."""
    waypoints, tol = params
    i, lap = state
    ni, nlap = next_state
    robot, = inputs
    k = i[b, 0]
    d0 = robot[b, 0] - waypoints[k, 0]
    d1 = robot[b, 1] - waypoints[k, 1]
    arrived = math.sqrt(d0 * d0 + d1 * d1) < tol
    nk = (k + 1) % waypoints.shape[0] if arrived else k
    nlap[b, 0] = lap[b, 0] + (1.0 if (arrived and nk == 0) else 0.0)
    ni[b, 0] = nk
