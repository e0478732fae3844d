"""Compiled kernels of the push tasks: each task's frame — the attempt-level state machine — one trial at a time.
They are the tasks' only implementation; their numpy references are in ``tests/reference/push_blocks.py``.

Every push task's state starts with the 7 common entries (``phase``, ``status``, ``attempt``, ``frames``,
``lost_frames``, ``target``, ``speed``) and its learning law's state, followed by 7 entries of its own; a kernel
copies the state to the next state, then works on the next state only (so the engine may pass the same arrays,
except for the side push answering dirt, whose kernel re-reads the state and says ``in_place=False``). A frame
is :func:`frame_begin` (lost-frame count; then, per trial, ``TRACKING_LOST``, ``SPHERE_LOST``, ``STALLED``), the
task's own step on a trial that is running, tracked and has its spheres, then :func:`frame_end` (the outputs).

The frames take a task's 15 entries with the law's first entry in the 8th place: ``law.x`` of the eq 13/18
integrator, ``law.x`` (``δ``) of the release-model law, whose ``law.neighbours`` comes as ``nb``, or ``law.theta``
of the curve-learning law, whose ``law.cov``, ``push_out`` and ``push_out_n`` come as three more arrays. Which law
the task has is ``p.law`` (:data:`~magctl.control.push_params.LAW_INTEGRATOR`, ``LAW_CURVE``, ``LAW_RELEASE``); a
task without the others' arrays is given small dummies, never read.

Parameters come as a :class:`~magctl.control.push_params.TaskParams` ``p`` read by field name (the task's record,
:mod:`magctl.control.push_params`, plus what it derives), the integrator's gain (length 1, or one per trial), for
the side push the tabulated model's arrays and the curve law's :class:`~magctl.control.kernels.CurveParams`
``cp``, for the front push the release law's tables. Side-push models (``F`` of eq 17) are a kind code:
:data:`~magctl.control.push_params.MODEL_EXP` (eq 22, ``p.m0`` = A, ``p.m1`` = k), ``MODEL_LIN`` (eq 23,
intercept, slope) or ``MODEL_TABLE`` (gaps, log displacements, rates). Status codes and phases are
:mod:`magctl.control.status`'s and :mod:`magctl.control.phases`'s.
"""

from __future__ import annotations

import math

import numba

from magctl.control.kernels import (
    curve_correction,
    curve_displacement,
    curve_gap,
    curve_update,
    law_gain,
    nan_max,
    nan_min,
    release_update,
)
from magctl.control.phases import (
    FINISHED,
    FRONT_PHASE_OFFSET,
    SIDE_PHASE_OFFSET,
    START,
    AssemblyStage,
    DirtStage,
    FrontPhase,
    SidePhase,
)
from magctl.control.push_params import LAW_CURVE, LAW_RELEASE, MODEL_EXP, MODEL_LIN
from magctl.control.status import Status

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
heavy = numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
"""A frame too large to inline: compiled once, called (inlining it would multiply compile time)."""

RUNNING, CONVERGED, ATTEMPT_LIMIT = int(Status.RUNNING), int(Status.CONVERGED), int(Status.ATTEMPT_LIMIT)
TRACKING_LOST, SPHERE_LOST, STALLED = int(Status.TRACKING_LOST), int(Status.SPHERE_LOST), int(Status.STALLED)
F_APPROACH, F_PUSH = int(FrontPhase.APPROACH), int(FrontPhase.PUSH)
F_RETRACT, F_SETTLE = int(FrontPhase.RETRACT), int(FrontPhase.SETTLE)
S_REPOSITION, S_PASS, S_SETTLE = int(SidePhase.REPOSITION), int(SidePhase.PASS), int(SidePhase.SETTLE)
DIRT_SIDE, DIRT_FRONT = int(DirtStage.SIDE), int(DirtStage.FRONT)
ASSEMBLY_FRONT, ASSEMBLY_SIDE = int(AssemblyStage.FRONT), int(AssemblyStage.SIDE)

AROUND_STEP = math.pi / 4
TWO_PI = 2 * math.pi


# --- planar helpers --------------------------------------------------------------------------------------
@jit
def norm2(x, y):
    """``norm``: ``sqrt(x² + y²)``."""
    return math.sqrt(x * x + y * y)


@jit
def unit2(x, y):
    """``unit``: the vector over its norm, ``(1, 0)`` where the norm is not positive."""
    n = norm2(x, y)
    if n > 0:
        return x / n, y / n
    return 1.0, 0.0


@jit
def arrived(r0, r1, t0, t1, tol):
    """``arrived``: robot within ``tol`` of the target."""
    return norm2(r0 - t0, r1 - t1) < tol


@jit
def sign(x):
    """``np.sign`` of a float (NaN stays NaN)."""
    if x > 0:
        return 1.0
    if x < 0:
        return -1.0
    return x


@jit
def around(r0, r1, o0, o1, t0, t1, clearance):
    """``around``: the next waypoint from the robot to the target keeping ``clearance`` from the obstacle
    (``π/4`` further round the ``1.08·clearance`` circle where the segment is blocked)."""
    d0 = t0 - r0
    d1 = t1 - r1
    rel0 = o0 - r0
    rel1 = o1 - r1
    dd = d0 * d0 + d1 * d1
    t = nan_min(nan_max((rel0 * d0 + rel1 * d1) / (dd if dd > 0 else 1.0), 0.0), 1.0)
    closest = norm2(r0 + t * d0 - o0, r1 + t * d1 - o1)
    if not (closest < clearance and norm2(t0 - o0, t1 - o1) >= clearance):
        return t0, t1
    a_r = math.atan2(r1 - o1, r0 - o0)
    a_t = math.atan2(t1 - o1, t0 - o0)
    diff = (a_t - a_r + math.pi) % TWO_PI - math.pi
    a = a_r + sign(diff) * nan_min(abs(diff), AROUND_STEP)
    rad = 1.08 * clearance
    return o0 + rad * math.cos(a), o1 + rad * math.sin(a)


@jit
def _cp(b, src, dst):
    for i in range(src.shape[1]):
        dst[b, i] = src[b, i]


@jit
def copy_task_state(b, st, nx):
    """The next state = the state (a push task's 15 entries)."""
    _cp(b, st[0], nx[0])
    _cp(b, st[1], nx[1])
    _cp(b, st[2], nx[2])
    _cp(b, st[3], nx[3])
    _cp(b, st[4], nx[4])
    _cp(b, st[5], nx[5])
    _cp(b, st[6], nx[6])
    _cp(b, st[7], nx[7])
    _cp(b, st[8], nx[8])
    _cp(b, st[9], nx[9])
    _cp(b, st[10], nx[10])
    _cp(b, st[11], nx[11])
    _cp(b, st[12], nx[12])
    _cp(b, st[13], nx[13])
    _cp(b, st[14], nx[14])


@jit
def copy3(b, st, nx):
    """The next state = the state (the curve law's ``law.cov``, ``push_out``, ``push_out_n``)."""
    _cp(b, st[0], nx[0])
    _cp(b, st[1], nx[1])
    _cp(b, st[2], nx[2])


# --- the frame shared by every push task (PushTask._frame, _fail, _enter, _finish_attempt) -----------------
@jit
def spheres_found(b, p, goal, sp):
    """``_spheres_found``: the pushed sphere finite and within ``workspace`` of the goal, or (assemblies) both
    spheres finite and within ``workspace`` of each other."""
    i = 2 * p.i0
    s0 = sp[b, i]
    s1 = sp[b, i + 1]
    if p.pair:
        j = 2 * p.i1
        q0 = sp[b, j]
        q1 = sp[b, j + 1]
        if not (math.isfinite(s0) and math.isfinite(s1) and math.isfinite(q0) and math.isfinite(q1)):
            return False
        return norm2(s0 - q0, s1 - q1) < p.workspace
    if not (math.isfinite(s0) and math.isfinite(s1)):
        return False
    return not (norm2(s0 - goal[b, 0], s1 - goal[b, 1]) > p.workspace)


@jit
def fail(b, status, target, code, r0, r1):
    """``_fail``: end the trial with ``code``, holding the robot where it is."""
    status[b, 0] = code
    target[b, 0] = r0
    target[b, 1] = r1


@jit
def enter(b, phase, frames, ph):
    """``_enter``: phase ``ph`` from frame 0."""
    phase[b, 0] = ph
    frames[b, 0] = 0


@jit
def finish_attempt(b, p, status, attempt, converged):
    """``_finish_attempt``: count the attempt; converged or the limit ends the trial. True: the trial goes on."""
    attempt[b, 0] += 1
    if converged:
        status[b, 0] = CONVERGED
        return False
    if attempt[b, 0] >= p.max_attempts:
        status[b, 0] = ATTEMPT_LIMIT
        return False
    return True


@jit
def frame_begin(b, p, phase, status, frames, lost_frames, target, r0, r1, lost, found):
    """``_frame`` before ``_step``: lost-frame count, then TRACKING_LOST, SPHERE_LOST, STALLED.
    True: the trial is running and tracked (its ``_step`` runs)."""
    running = status[b, 0] == RUNNING
    lost_frames[b, 0] = lost_frames[b, 0] + 1 if (running and lost) else 0
    if running:
        frames[b, 0] += 1
    if running and lost_frames[b, 0] > p.max_lost_frames:
        fail(b, status, target, TRACKING_LOST, r0, r1)
    if status[b, 0] == RUNNING and not lost and not found:
        fail(b, status, target, SPHERE_LOST, r0, r1)
    if status[b, 0] == RUNNING and frames[b, 0] > p.phase_timeout_frames:
        fail(b, status, target, STALLED, r0, r1)
    return status[b, 0] == RUNNING and not lost


@jit
def frame_end(b, phase, status, attempt, target, speed, correction, r0, r1):
    """``_frame`` after ``_step``: FINISHED phase, the outputs (target, NaN → robot; speed cap 0 when done; the
    law's output ``correction``)."""
    done = status[b, 0] != RUNNING
    if done:
        phase[b, 0] = FINISHED
    t0 = target[b, 0]
    t1 = target[b, 1]
    return (r0 if math.isnan(t0) else t0, r1 if math.isnan(t1) else t1, 0.0 if done else speed[b, 0],
            status[b, 0], attempt[b, 0], phase[b, 0], correction)


@jit
def write_outputs(b, outputs, out):
    """The 6 outputs every push task has: target, speed_cap, status, attempt, phase, correction."""
    outputs[0][b, 0] = out[0]
    outputs[0][b, 1] = out[1]
    outputs[1][b, 0] = out[2]
    outputs[2][b, 0] = out[3]
    outputs[3][b, 0] = out[4]
    outputs[4][b, 0] = out[5]
    outputs[5][b, 0] = out[6]


# --- front push (front.py) -------------------------------------------------------------------------------
@jit
def front_geometry(b, p, goal, sp):
    """``_geometry``: sphere, goal point, unit pushing direction and eq 12 (front push), or for the front
    assembly the contact point of sphere 2 and eq 21."""
    i = 2 * p.i0
    s0 = sp[b, i]
    s1 = sp[b, i + 1]
    if p.pair:
        j = 2 * p.i1
        q0 = sp[b, j]
        q1 = sp[b, j + 1]
        v0, v1 = unit2(q0 - s0, q1 - s1)
        rs = p.r0 + p.r1
        done = norm2(q0 - s0, q1 - s1) <= rs + p.eps_as
        return s0, s1, q0 - rs * v0, q1 - rs * v1, v0, v1, done
    g0 = goal[b, 0]
    g1 = goal[b, 1]
    u0, u1 = unit2(g0 - s0, g1 - s1)
    return s0, s1, g0, g1, u0, u1, norm2(g0 - s0, g1 - s1) < p.eps


@heavy
def front_frame(b, p, gain, rel, st, nb, r0, r1, sp, lost):
    """One frame of :class:`~magctl.control.push.front.FrontPushTask` (and the front assembly) on the next state
    ``st``: approach → push (eq 10, 11) → retract → settle → eq 12 / eq 13, or with the release-model law
    (``p.law``, tables ``rel``, neighbours ``nb``) ``δ ← δ*(|e|, e + δ)`` in eq 13's place. Returns the
    outputs."""
    phase, status, attempt, frames, lost_frames, target, speed, lawx, goal, u, p_ri, p_o, g_line, stand, back = st
    found = spheres_found(b, p, goal, sp)
    if frame_begin(b, p, phase, status, frames, lost_frames, target, r0, r1, lost, found):
        ph = phase[b, 0]
        s0, s1, g0, g1, u0, u1, done = front_geometry(b, p, goal, sp)
        begin = False
        if ph == START:
            if done:
                status[b, 0] = CONVERGED
            else:
                begin = True
        elif ph == F_APPROACH:
            if arrived(r0, r1, p_ri[b, 0], p_ri[b, 1], p.arrive_tol):
                enter(b, phase, frames, F_PUSH)
        elif ph == F_PUSH:
            if norm2(s0 - p_o[b, 0], s1 - p_o[b, 1]) < p.push_tol or \
                    arrived(r0, r1, stand[b, 0], stand[b, 1], p.arrive_tol):
                back[b, 0] = r0 - p.retract * u[b, 0]
                back[b, 1] = r1 - p.retract * u[b, 1]
                enter(b, phase, frames, F_RETRACT)
        elif ph == F_RETRACT:
            if arrived(r0, r1, back[b, 0], back[b, 1], p.arrive_tol):
                enter(b, phase, frames, F_SETTLE)
        elif ph == F_SETTLE:
            if frames[b, 0] >= p.settle_frames:
                e = (g_line[b, 0] - s0) * u[b, 0] + (g_line[b, 1] - s1) * u[b, 1]
                if finish_attempt(b, p, status, attempt, done):
                    if p.law == LAW_RELEASE:
                        release_update(b, rel[0], rel[1], rel[2], rel[3], rel[4], rel[5], lawx, nb, e)
                    else:
                        lawx[b, 0] = lawx[b, 0] + law_gain(gain, b) * e   # eq 13
                    begin = True
        if begin:  # _begin: the attempt's line, P_o = P_g + δu (eq 10), P_ri and where the robot stands
            delta = lawx[b, 0]
            po0 = g0 + delta * u0
            po1 = g1 + delta * u1
            u[b, 0] = u0
            u[b, 1] = u1
            g_line[b, 0] = g0
            g_line[b, 1] = g1
            p_ri[b, 0] = s0 - p.approach * u0
            p_ri[b, 1] = s1 - p.approach * u1
            p_o[b, 0] = po0
            p_o[b, 1] = po1
            stand[b, 0] = po0 - p.contact * u0
            stand[b, 1] = po1 - p.contact * u1
            enter(b, phase, frames, F_APPROACH)
        ph = phase[b, 0]  # _targets
        if ph == F_APPROACH:
            t0, t1 = around(r0, r1, s0, s1, p_ri[b, 0], p_ri[b, 1], p.clearance)
            target[b, 0] = t0
            target[b, 1] = t1
        elif ph == F_PUSH:
            target[b, 0] = stand[b, 0]
            target[b, 1] = stand[b, 1]
        elif ph == F_RETRACT or ph == F_SETTLE:
            target[b, 0] = back[b, 0]
            target[b, 1] = back[b, 1]
        speed[b, 0] = p.push_speed if ph == F_PUSH else p.travel_speed
    return frame_end(b, phase, status, attempt, target, speed, lawx[b, 0], r0, r1)


@jit
def front_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.front.FrontPushTask` / ``FrontAssemblyTask`` step with the eq 13 law."""
    p, gain, rs, rd, rx0, rx1, rrow, rhit, nb = params
    robot, sp, lost = inputs
    copy_task_state(b, state, next_state)
    out = front_frame(b, p, gain, (rs, rd, rx0, rx1, rrow, rhit), next_state, nb, robot[b, 0], robot[b, 1],
                      sp, lost[b, 0])
    write_outputs(b, outputs, out)


@jit
def release_front_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.front.FrontPushTask` step with the release-model law (``learning="release"``):
    its state has ``law.neighbours`` after ``law.x``."""
    p, gain, rs, rd, rx0, rx1, rrow, rhit = params
    robot, sp, lost = inputs
    st = next_state[0:8] + next_state[9:16]
    copy_task_state(b, state[0:8] + state[9:16], st)
    _cp(b, state[8], next_state[8])
    out = front_frame(b, p, gain, (rs, rd, rx0, rx1, rrow, rhit), st, next_state[8], robot[b, 0], robot[b, 1],
                      sp, lost[b, 0])
    write_outputs(b, outputs, out)


# --- side push (side.py, assembly.py) ----------------------------------------------------------------------
@jit
def side_geometry(b, p, goal, sp, r0, r1):
    """``_geometry``: sphere, distance still to go, pushing direction and side of the robot, eq 12 (side
    push); for the assembly the adjusted line at ``θ_n``, the gap still to close and eq 21."""
    i = 2 * p.i0
    s0 = sp[b, i]
    s1 = sp[b, i + 1]
    if p.pair:
        j = 2 * p.i1
        q0 = sp[b, j]
        q1 = sp[b, j + 1]
        v0, v1 = unit2(q0 - s0, q1 - s1)
        side = 1.0 if v0 * (r1 - s1) - v1 * (r0 - s0) >= 0 else -1.0
        angle = side * p.theta_n
        c = math.cos(angle)
        s = math.sin(angle)
        sep = norm2(q0 - s0, q1 - s1)
        to_close = nan_max(sep - p.r0 - p.r1, 0.0)
        done = sep <= p.r0 + p.r1 + p.eps_as
        return s0, s1, to_close, c * v0 - s * v1, s * v0 + c * v1, side, done
    d0 = goal[b, 0] - s0
    d1 = goal[b, 1] - s1
    u0, u1 = unit2(d0, d1)
    side = 1.0 if u0 * (r1 - s1) - u1 * (r0 - s0) >= 0 else -1.0
    dist = norm2(d0, d1)
    return s0, s1, dist, u0, u1, side, dist < p.eps


@jit
def model_gap(p, tg, tld, trate, ds):
    """``F(D_s)`` of eq 17: eq 22 (``−ln(D_s/A)/k``), eq 23 (affine) or the tabulated model; ``D_s ≤ 0`` (and
    NaN) gives an infinite gap for eq 22 and the table."""
    kind = p.model
    if kind == MODEL_LIN:
        return p.m0 + p.m1 * ds
    if kind == MODEL_EXP:
        if ds > 0:
            return -math.log(ds / p.m0) / p.m1
        return math.inf
    if not ds > 0:
        return math.inf
    x = math.log(ds)
    k = 0  # searchsorted(-ld, -x) − 1, clipped to the segments
    for m in range(tld.shape[0]):
        if tld[m] > x:
            k += 1
    k = min(max(k - 1, 0), tg.shape[0] - 2)
    return tg[k] + (x - tld[k]) / trate[k]


@jit
def learn_push_out(b, p, u, p0, start, push_out, push_out_n, s0, s1):
    """The push-out ratio learned from a pass: the sphere's displacement across the pass, away from the robot's side,
    over its displacement along it (a pass at least ``push_out_min`` long), taken whole the first time and with
    ``push_out_weight`` after."""
    u0 = u[b, 0]
    u1 = u[b, 1]
    d0 = s0 - p0[b, 0]
    d1 = s1 - p0[b, 1]
    w0 = start[b, 0] - p0[b, 0] + p.behind * u0
    w1 = start[b, 1] - p0[b, 1] + p.behind * u1
    robot_side = sign(w0 * -u1 + w1 * u0)
    along = d0 * u0 + d1 * u1
    across = -robot_side * (d0 * -u1 + d1 * u0)
    if along >= p.push_out_min:
        ratio = across / along
        weight = 1.0 if push_out_n[b, 0] == 0 else p.push_out_weight
        push_out[b, 0] = push_out[b, 0] + weight * (ratio - push_out[b, 0])
        push_out_n[b, 0] += 1


@heavy
def side_frame(b, p, gain, tg, tld, trate, cp, st, cov, push_out, push_out_n, r0, r1, sp, lost):
    """One frame of :class:`~magctl.control.push.side.SidePushTask` (and the side-push assembly) on the next
    state ``st``: reposition → pass → settle → eq 12 (eq 21) / eq 18, or with the curve-learning law
    (``p.law``; ``st``'s 8th entry is ``law.theta``, then ``law.cov``, ``push_out``, ``push_out_n``) the EKF
    step, the push-out ratio, the estimate's bound and inverse for ``D_s,des`` and ``D_g`` and the pass turned
    by ``atan`` of the push-out. Returns the outputs and the gap output."""
    phase, status, attempt, frames, lost_frames, target, speed, lawx, goal, u, p0, start, end, d_des, gap = st
    curve = p.law == LAW_CURVE
    found = spheres_found(b, p, goal, sp)
    if frame_begin(b, p, phase, status, frames, lost_frames, target, r0, r1, lost, found):
        ph = phase[b, 0]
        s0, s1, dist, u0, u1, side, done = side_geometry(b, p, goal, sp, r0, r1)
        begin = False
        if ph == START:
            if done:
                status[b, 0] = CONVERGED
            else:
                begin = True
        elif ph == S_REPOSITION:
            if arrived(r0, r1, start[b, 0], start[b, 1], p.arrive_tol):
                enter(b, phase, frames, S_PASS)
        elif ph == S_PASS:
            if arrived(r0, r1, end[b, 0], end[b, 1], p.arrive_tol):
                enter(b, phase, frames, S_SETTLE)
        elif ph == S_SETTLE:
            if frames[b, 0] >= p.settle_frames:
                d_act = (s0 - p0[b, 0]) * u[b, 0] + (s1 - p0[b, 1]) * u[b, 1]
                if finish_attempt(b, p, status, attempt, done):
                    if curve:  # the pass (D_g, D_s,act) into the estimate, then its push-out
                        curve_update(b, cp, p.iterations, lawx, cov, lawx, cov, gap[b, 0], d_act)
                        learn_push_out(b, p, u, p0, start, push_out, push_out_n, s0, s1)
                    else:
                        lawx[b, 0] = lawx[b, 0] + law_gain(gain, b) * (d_act - d_des[b, 0])   # eq 18
                    begin = True
        if begin:  # _begin: eq 16 (bounded), eq 17, the motion line; no pass for an infinite gap
            if curve:  # the estimate's own bound; the pass turned against the push-out
                turn = math.atan(push_out[b, 0])
                c = math.cos(turn)
                sn = side * math.sin(turn)
                u0, u1 = c * u0 + sn * -u1, c * u1 + sn * u0
                dd = nan_min(dist, curve_displacement(lawx, b, cp, p.min_gap))
            else:
                dd = nan_min(dist, p.d_max)
            if p.fixed:
                g = p.fixed_gap
            elif curve:
                g = curve_gap(lawx, b, cp, dd, p.min_gap)
            else:
                g = nan_max(model_gap(p, tg, tld, trate, dd + lawx[b, 0]), p.min_gap)
            finite = math.isfinite(g)
            gg = g if finite else 0.0
            n0 = side * -u1 * gg
            n1 = side * u0 * gg
            u[b, 0] = u0
            u[b, 1] = u1
            p0[b, 0] = s0
            p0[b, 1] = s1
            start[b, 0] = s0 - p.behind * u0 + n0
            start[b, 1] = s1 - p.behind * u1 + n1
            if finite:
                end[b, 0] = s0 + p.ahead * u0 + n0
                end[b, 1] = s1 + p.ahead * u1 + n1
            else:
                end[b, 0] = r0
                end[b, 1] = r1
            d_des[b, 0] = dd
            gap[b, 0] = g
            enter(b, phase, frames, S_REPOSITION if finite else S_SETTLE)
        ph = phase[b, 0]
        if ph == S_REPOSITION:
            t0, t1 = around(r0, r1, s0, s1, start[b, 0], start[b, 1], p.clearance)
            target[b, 0] = t0
            target[b, 1] = t1
        elif ph == S_PASS or ph == S_SETTLE:
            target[b, 0] = end[b, 0]
            target[b, 1] = end[b, 1]
        speed[b, 0] = p.pass_speed if ph == S_PASS else p.travel_speed
    g = gap[b, 0]
    correction = curve_correction(lawx, b, cp) if curve else lawx[b, 0]
    return frame_end(b, phase, status, attempt, target, speed, correction, r0, r1), 0.0 if math.isinf(g) else g


@jit
def side_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.side.SidePushTask` / ``AssemblyTask`` step with the eq 18 law."""
    p, gain, tg, tld, trate, cp, cov, push_out, push_out_n = params
    robot, sp, lost = inputs
    copy_task_state(b, state, next_state)
    out, g = side_frame(b, p, gain, tg, tld, trate, cp, next_state, cov, push_out, push_out_n, robot[b, 0],
                        robot[b, 1], sp, lost[b, 0])
    write_outputs(b, outputs, out)
    outputs[6][b, 0] = g


@jit
def curve_side_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.side.SidePushTask` / ``AssemblyTask`` step with the curve-learning law: the
    state has ``law.theta``, ``law.cov``, ``push_out``, ``push_out_n`` before the task's own 7 entries."""
    p, gain, tg, tld, trate, cp = params
    robot, sp, lost = inputs
    st = next_state[0:8] + next_state[11:18]
    extra = next_state[8:11]
    copy_task_state(b, state[0:8] + state[11:18], st)
    copy3(b, state[8:11], extra)
    out, g = side_frame(b, p, gain, tg, tld, trate, cp, st, extra[0], extra[1], extra[2], robot[b, 0],
                        robot[b, 1], sp, lost[b, 0])
    write_outputs(b, outputs, out)
    outputs[6][b, 0] = g


# --- side push answering dirt with a front push (side.py, dirt_response="front") ---------------------------
@jit
def reset_front(b, st, x0):
    """A front push's initial state (``FrontPushTask.initial_state``; its goal, never changed, is kept)."""
    phase, status, attempt, frames, lost_frames, target, speed, lawx, goal, u, p_ri, p_o, g_line, stand, back = st
    phase[b, 0] = START
    status[b, 0] = RUNNING
    attempt[b, 0] = 0
    frames[b, 0] = 0
    lost_frames[b, 0] = 0
    target[b, 0] = math.nan
    target[b, 1] = math.nan
    speed[b, 0] = 0.0
    lawx[b, 0] = x0
    for i in range(2):
        u[b, i] = 0.0
        p_ri[b, i] = 0.0
        p_o[b, i] = 0.0
        g_line[b, i] = 0.0
        stand[b, i] = 0.0
        back[b, i] = 0.0


@jit
def restart_side(b, st):
    """The side passes start afresh (``phase`` START, ``frames`` 0, no target)."""
    phase, status, attempt, frames, lost_frames, target = st[0:6]
    phase[b, 0] = START
    frames[b, 0] = 0
    target[b, 0] = math.nan
    target[b, 1] = math.nan


@heavy
def side_dirt_frame(b, p, gain, tg, tld, trate, cp, front_p, fgain, rel, fnb, fx0, state, next_state, robot,
                    sp, lost, outputs):
    """The side push answering dirt, for trial ``b``: the side frame, and on the frame it measures a sphere
    the curve law reads as stuck (mobility at ``min_gap`` under ``[dirt] mobility``, more than ``[dirt] passes``
    passes to go, fewer than ``[dirt] fronts`` front pushes so far) — or, with ``front_first``, on its first
    frame — the hand-over to a fresh front push (eq 10–13,
    no learning); while it runs the side stage is frozen (its frame is stepped on a scratch copy: its phase is the
    output on the frame the front push ends), and its end counts as an attempt (eq 12), or ends the task with its
    failure."""
    side_in = state[0:8] + state[28:35]
    side = next_state[0:8] + next_state[28:35]
    extra_in = state[8:11]
    extra = next_state[8:11]
    front_in = state[13:28]
    front = next_state[13:28]
    stage, fronts = state[11], state[12]
    nstage, nfronts = next_state[11], next_state[12]
    copy_task_state(b, side_in, side)
    copy3(b, extra_in, extra)
    copy_task_state(b, front_in, front)
    nstage[b, 0] = stage[b, 0]
    nfronts[b, 0] = fronts[b, 0]
    r0 = robot[b, 0]
    r1 = robot[b, 1]
    in_front = stage[b, 0] == DIRT_FRONT
    s_out, g = side_frame(b, p, gain, tg, tld, trate, cp, side, extra[0], extra[1], extra[2], r0, r1, sp, lost)
    i = 2 * p.i0
    goal = side[8]
    dist = norm2(goal[b, 0] - sp[b, i], goal[b, 1] - sp[b, i + 1])
    status, attempt = side[1], side[2]
    t0, t1, spd, phase_out = s_out[0], s_out[1], s_out[2], s_out[5]
    trigger = False
    ended = False
    if in_front:
        f = front_frame(b, front_p, fgain, rel, front, fnb, r0, r1, sp, lost)
        copy_task_state(b, side_in, side)   # the side stage is frozen while the front push runs
        copy3(b, extra_in, extra)
        ended = f[3] != RUNNING
        if ended:
            if f[3] == CONVERGED or f[3] == ATTEMPT_LIMIT:  # back to side passes: the front push was an attempt
                restart_side(b, side)
                finish_attempt(b, p, status, attempt, dist < p.eps)
            else:
                status[b, 0] = f[3]
            nstage[b, 0] = DIRT_SIDE
        else:
            t0, t1, spd, phase_out = f[0], f[1], f[2], f[5] + FRONT_PHASE_OFFSET
        g = 0.0
    else:
        if p.front_first and fronts[b, 0] == 0 and attempt[b, 0] == 0 and status[b, 0] == RUNNING:
            trigger = True   # the coarse move first: a front push before any side pass
        elif attempt[b, 0] > side_in[2][b, 0] and status[b, 0] == RUNNING:  # an attempt was just measured
            d_min = curve_displacement(side[7], b, cp, p.min_gap)
            stuck = d_min / p.prior_at_min_gap < p.dirt_mobility
            many = dist > p.dirt_passes * d_min
            trigger = stuck and many and fronts[b, 0] < p.max_fronts
        if trigger:
            restart_side(b, side)
            reset_front(b, front, fx0)
            nstage[b, 0] = DIRT_FRONT
            nfronts[b, 0] = fronts[b, 0] + 1
    if status[b, 0] != RUNNING:
        side[0][b, 0] = FINISHED
        phase_out = FINISHED
    if ended or trigger:
        t0, t1, spd = r0, r1, 0.0
    write_outputs(b, outputs, (t0, t1, spd, status[b, 0], attempt[b, 0], phase_out, s_out[6]))
    outputs[6][b, 0] = g


@jit
def side_dirt_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.side.SidePushTask` with the curve-learning law and ``dirt_response="front"``
    (``in_place=False``: the frozen side stage is re-read from the state)."""
    p, gain, tg, tld, trate, cp, front_p, fgain, rs, rd, rx0, rx1, rrow, rhit, fnb, fx0 = params
    robot, sp, lost = inputs
    side_dirt_frame(b, p, gain, tg, tld, trate, cp, front_p, fgain, (rs, rd, rx0, rx1, rrow, rhit), fnb, fx0,
                    state, next_state, robot, sp, lost[b, 0], outputs)


# --- front push, then side-push assembly (assembly.py, Fig 15) ------------------------------------------
@jit
def front_then_side(b, fparams, sparams, stage, nstage, fst, sst, extra, robot, sp, lost, outputs):
    """:class:`~magctl.control.push.assembly.FrontThenSideAssemblyTask` on the next state: the front stage every
    frame, the side stage (advanced) only in stage 2, which starts the frame after the front stage hits its
    attempt limit."""
    front_p, fgain, rel, fnb = fparams
    side_p, sgain, tg, tld, trate, cp = sparams
    r0 = robot[b, 0]
    r1 = robot[b, 1]
    in_side = stage[b, 0] == ASSEMBLY_SIDE
    f = front_frame(b, front_p, fgain, rel, fst, fnb, r0, r1, sp, lost)
    if in_side:
        s, g = side_frame(b, side_p, sgain, tg, tld, trate, cp, sst, extra[0], extra[1], extra[2], r0, r1, sp,
                          lost)
        ph = s[5] + SIDE_PHASE_OFFSET if s[5] != FINISHED else s[5]
        write_outputs(b, outputs, (s[0], s[1], s[2], s[3], f[4] + s[4], ph, s[6]))
        outputs[6][b, 0] = g
        outputs[7][b, 0] = ASSEMBLY_SIDE
        nstage[b, 0] = ASSEMBLY_SIDE
        return
    write_outputs(b, outputs, f)
    outputs[6][b, 0] = 0.0
    outputs[7][b, 0] = ASSEMBLY_FRONT
    if f[3] == ATTEMPT_LIMIT:  # handover: stage 2 from the next frame
        outputs[2][b, 0] = RUNNING
        outputs[4][b, 0] = SIDE_PHASE_OFFSET
        nstage[b, 0] = ASSEMBLY_SIDE
    else:
        nstage[b, 0] = ASSEMBLY_FRONT


@jit
def front_then_side_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.assembly.FrontThenSideAssemblyTask` with the eq 18 law in the side stage."""
    (front_p, fgain, rs, rd, rx0, rx1, rrow, rhit, fnb,
     side_p, sgain, tg, tld, trate, cp, cov, push_out, push_out_n) = params
    robot, sp, lost = inputs
    fst = next_state[1:16]
    sst = next_state[16:31]
    copy_task_state(b, state[1:16], fst)
    copy_task_state(b, state[16:31], sst)
    front_then_side(b, (front_p, fgain, (rs, rd, rx0, rx1, rrow, rhit), fnb), (side_p, sgain, tg, tld, trate, cp),
                    state[0], next_state[0], fst, sst, (cov, push_out, push_out_n), robot, sp, lost[b, 0], outputs)


@jit
def front_then_curve_side_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.assembly.FrontThenSideAssemblyTask` with the curve-learning law in the side
    stage (its state has ``law.theta``, ``law.cov``, ``push_out``, ``push_out_n``)."""
    front_p, fgain, rs, rd, rx0, rx1, rrow, rhit, fnb, side_p, sgain, tg, tld, trate, cp = params
    robot, sp, lost = inputs
    fst = next_state[1:16]
    sst = next_state[16:24] + next_state[27:34]
    extra = next_state[24:27]
    copy_task_state(b, state[1:16], fst)
    copy_task_state(b, state[16:24] + state[27:34], sst)
    copy3(b, state[24:27], extra)
    front_then_side(b, (front_p, fgain, (rs, rd, rx0, rx1, rrow, rhit), fnb), (side_p, sgain, tg, tld, trate, cp),
                    state[0], next_state[0], fst, sst, extra, robot, sp, lost[b, 0], outputs)


# --- planned assembly (planned.py): the frames compiled, the plan a Python event ----------------------------
@jit
def spheres_inside(b, area, sp):
    """``PlannedAssemblyTask._spheres_found``: every sphere finite and inside ``area`` = (x0, y0, x1, y1), the
    planner's field widened by the workspace margin."""
    for k in range(sp.shape[1] // 2):
        x = sp[b, 2 * k]
        y = sp[b, 2 * k + 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            return False
        if not (area[0] < x < area[2] and area[1] < y < area[3]):
            return False
    return True


@jit
def assembled(b, bonds, contact, shape, sp):
    """:meth:`~magctl.control.arrangement.Arrangement.assembled`: eq 21 on every contact bond
    (``|P_j − P_i| ≤ L_ij + ε_as``), the shape bonds at least ``L_ij·cos(bend/2)``; ``shape`` = (ε_as, cos(bend/2))."""
    for k in range(bonds.shape[0]):
        i = 2 * int(bonds[k, 0])
        j = 2 * int(bonds[k, 1])
        dist = norm2(sp[b, j] - sp[b, i], sp[b, j + 1] - sp[b, i + 1])
        if contact[k]:
            if not dist <= bonds[k, 2] + shape[0]:
                return False
        elif not dist >= bonds[k, 2] * shape[1]:
            return False
    return True


@jit
def planned_step(b, params, state, next_state, inputs, outputs, base, noise):
    """:class:`~magctl.control.push.planned.PlannedAssemblyTask`'s frame: reposition along the waypoints → pass →
    settle → eq 21 on every bond. A trial that needs a pass (its first, or the next after a measured one) raises
    ``plan_due``; the task's ``handle_event`` plans it in Python at the end of the frame, so the pass and its path
    apply from the next frame on (the plan takes one frame, as on a rig)."""
    p, area, bonds, contact, shape, waypoint_tol = params
    robot, sp, lost = inputs
    copy_planned_state(b, state, next_state)
    (phase, status, attempt, frames, lost_frames, target, speed, _start, _end, _before, _predicted, error,
     _mobility, _weight, _passes, waypoints, n_waypoints, waypoint, start, end, gap, due) = next_state
    r0 = robot[b, 0]
    r1 = robot[b, 1]
    found = spheres_inside(b, area, sp)
    if frame_begin(b, p, phase, status, frames, lost_frames, target, r0, r1, lost[b, 0], found):
        ph = phase[b, 0]
        done = assembled(b, bonds, contact, shape, sp)
        if ph == START:
            if done:
                status[b, 0] = CONVERGED
            else:
                due[b, 0] = True
        elif ph == S_REPOSITION:
            k = min(waypoint[b, 0], waypoints.shape[1] // 2 - 1)
            w0 = waypoints[b, 2 * k]
            w1 = waypoints[b, 2 * k + 1]
            last = waypoint[b, 0] >= n_waypoints[b, 0] - 1
            tol = p.arrive_tol if last else waypoint_tol
            if norm2(r0 - (0.0 if math.isnan(w0) else w0), r1 - (0.0 if math.isnan(w1) else w1)) < tol:
                if last:
                    enter(b, phase, frames, S_PASS)
                else:
                    waypoint[b, 0] += 1
        elif ph == S_PASS:
            if arrived(r0, r1, end[b, 0], end[b, 1], p.arrive_tol):
                enter(b, phase, frames, S_SETTLE)
        elif ph == S_SETTLE:
            if frames[b, 0] >= p.settle_frames:
                if finish_attempt(b, p, status, attempt, done):
                    due[b, 0] = True
        ph = phase[b, 0]
        if ph == S_REPOSITION:
            k = min(waypoint[b, 0], waypoints.shape[1] // 2 - 1)
            target[b, 0] = waypoints[b, 2 * k]
            target[b, 1] = waypoints[b, 2 * k + 1]
        elif ph == S_PASS or ph == S_SETTLE:
            target[b, 0] = end[b, 0]
            target[b, 1] = end[b, 1]
        speed[b, 0] = p.pass_speed if ph == S_PASS else p.travel_speed
    e = error[b, 0]
    out = frame_end(b, phase, status, attempt, target, speed, 0.0 if math.isnan(e) else e, r0, r1)
    write_outputs(b, outputs, out)
    g = gap[b, 0]
    outputs[6][b, 0] = 0.0 if math.isnan(g) else g


@jit
def copy_planned_state(b, st, nx):
    """The next state = the state (the planned assembly's 22 entries)."""
    copy_task_state(b, st[0:15], nx[0:15])
    _cp(b, st[15], nx[15])
    _cp(b, st[16], nx[16])
    _cp(b, st[17], nx[17])
    _cp(b, st[18], nx[18])
    _cp(b, st[19], nx[19])
    _cp(b, st[20], nx[20])
    _cp(b, st[21], nx[21])
