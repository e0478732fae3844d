"""Kernels of the stand-in plant's blocks (:mod:`magctl.plant.standin`): the blocks' only implementation,
run by both engines (the interpreted one through :mod:`magctl.core.kernel_driver`).

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy reference (``tests/reference/plant_blocks.py``;
``_norm``'s ``einsum`` over two elements is ``x₀x₀ + x₁x₁``; ``np.arctan2`` is ``math.atan2``;
``np.minimum``/``np.maximum`` keep numpy's NaN rule). Imported when a block first runs, so that numba
stays out of the import of ``magctl``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from magctl.core.philox import normal

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")


# --- the robot ------------------------------------------------------------------------------------------
@jit
def kinematic_robot_output(b, params, state, outputs):
    """``KinematicRobot.output``: position, heading and velocity of the state."""
    x, h, v = state
    position, heading, velocity = outputs
    position[b, 0] = x[b, 0]
    position[b, 1] = x[b, 1]
    heading[b, 0] = h[b, 0]
    velocity[b, 0] = v[b, 0]
    velocity[b, 1] = v[b, 1]


@jit
def _kinematic_move(b, dt, state, next_state, speed, heading, steer):
    """``x[k+1] = x[k] + T·v``, ``v = speed·(cos h, sin h)``; the heading follows the input while steering."""
    x, h, v = state
    nx, nh, nv = next_state
    hd = heading[b, 0]
    v0 = speed[b, 0] * np.cos(hd)
    v1 = speed[b, 0] * np.sin(hd)
    nx[b, 0] = x[b, 0] + dt * v0
    nx[b, 1] = x[b, 1] + dt * v1
    nh[b, 0] = hd if steer else h[b, 0]
    nv[b, 0] = v0
    nv[b, 1] = v1


@jit
def kinematic_robot_update(b, params, state, next_state, inputs, base, noise):
    """``KinematicRobot.update`` without a ``steer`` input: the heading follows the input while ``speed > 0``."""
    dt, = params
    speed, heading = inputs
    _kinematic_move(b, dt, state, next_state, speed, heading, speed[b, 0] > 0)


@jit
def kinematic_robot_steer_update(b, params, state, next_state, inputs, base, noise):
    """``KinematicRobot.update`` with the ``steer`` input: the heading follows the input while it is true."""
    dt, = params
    speed, heading, steer = inputs
    _kinematic_move(b, dt, state, next_state, speed, heading, steer[b, 0])


@jit
def field_gait_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``FieldGait.output``: heading along ``b_static``; speed ``v = f·s(θ_a)`` of
    ``magctl.plant._stickslip.speed`` (``θ_a = atan(|b_osc|/|B_xy|)/√(1 + (2πf τ_θ)²)``,
    ``τ_θ = c_θ ζ/(m |B_xy|)``, ``s = η ℓ [cos θ_0 − cos θ_a]₊``) where ``|B_xy| > 0``, else 0."""
    drag, moment, eta_len, cos_break = params    # c_θ·ζ, m, η·ℓ, cos θ_0
    bs, bosc, freq = inputs
    speed, heading, steer = outputs
    b0, b1 = bs[b, 0], bs[b, 1]
    b_xy = np.sqrt(b0 * b0 + b1 * b1)
    on = b_xy > 0
    f = np.maximum(freq[b, 0], 0.0)
    bx = np.maximum(b_xy, 1e-9)
    tau = drag / (moment * bx)
    w = 2.0 * np.pi * f * tau
    theta_a = np.arctan(np.abs(bosc[b, 0]) / bx) / np.sqrt(1.0 + w * w)
    v = f * (eta_len * np.maximum(cos_break - np.cos(theta_a), 0.0))
    speed[b, 0] = v if on else 0.0
    heading[b, 0] = math.atan2(b1, b0)
    steer[b, 0] = on


@jit
def straight_to_target_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``StraightToTarget.output``: ``speed = min(cap, ‖target − x‖/T)``, ``cap = min(speed_cap, v_max)``
    (0 when ``speed_cap ≤ 0``), heading towards the target."""
    v_max, dt = params
    target, cap_in, position = inputs
    speed, heading = outputs
    d0 = target[b, 0] - position[b, 0]
    d1 = target[b, 1] - position[b, 1]
    c = cap_in[b, 0]
    cap = np.minimum(c, v_max) if c > 0 else 0.0
    speed[b, 0] = np.minimum(cap, np.sqrt(d0 * d0 + d1 * d1) / dt)
    heading[b, 0] = math.atan2(d1, d0)


# --- the spheres ------------------------------------------------------------------------------------------
@jit
def standin_spheres_output(b, params, state, outputs):
    """``StandinSpheres.output``: centres, contact flag, release count and last release amount."""
    s, contact, r, direction, attached, pending, passed, releases, last_release, k = state
    spheres, touching, n_rel, last = outputs
    for i in range(spheres.shape[1]):
        spheres[b, i] = s[b, i]
    touching[b, 0] = contact[b, 0]
    n_rel[b, 0] = releases[b, 0]
    last[b, 0] = last_release[b, 0]


@jit
def standin_spheres_update(b, params, state, next_state, inputs, base, noise):
    """``StandinSpheres.update``, sphere by sphere: the side pass of eq 22, the release ``D_p,r``
    (§IV-D: one standard normal draw at position ``k`` per frame), contact carried along the path or
    pushed out, then sphere–sphere separation of the sphere the robot did not drive. ``driven`` (one
    flag per sphere) is a work array, rewritten by every call."""
    (n, contact_distance, release_mean, release_std, side_range, side_a, side_k, scales, gap, straight_cos,
     driven) = params
    s, contact, r, direction, attached, pending, passed, releases, last_release, k = state
    ns, ncontact, nr, ndir, nattached, npending, npassed, nreleases, nlast, nk = next_state
    position, = inputs
    # read the trial's scalars, then work on the next state (the same arrays when in place)
    draw = normal(noise, b, k[b, 0], 0)
    r00, r01 = r[b, 0], r[b, 1]
    dir0, dir1 = direction[b, 0], direction[b, 1]
    rx, ry = position[b, 0], position[b, 1]
    rel_count = releases[b, 0]
    last = last_release[b, 0]
    for i in range(ns.shape[1]):
        ns[b, i] = s[b, i]
    for i in range(n):
        nattached[b, i] = attached[b, i]
        npending[b, i] = pending[b, i]
        npassed[b, i] = passed[b, i]
    ncontact[b, 0] = contact[b, 0]
    nr[b, 0] = rx
    nr[b, 1] = ry
    nk[b, 0] = k[b, 0] + 1
    if n == 0:
        return
    st0, st1 = rx - r00, ry - r01
    size = np.sqrt(st0 * st0 + st1 * st1)
    moving = size > 1e-12
    d0 = st0 / size if moving else 0.0
    d1 = st1 / size if moving else 0.0
    straight = moving and (d0 * dir0 + d1 * dir1) > straight_cos
    amp = side_a * (scales[b] if scales.shape[0] > 1 else scales[0])
    amount = np.maximum(0.0, release_mean + release_std * draw)
    c = contact_distance
    any_release = False
    any_over = False
    n_release = 0
    for i in range(n):
        sx, sy = ns[b, 2 * i], ns[b, 2 * i + 1]
        was_passed = npassed[b, i] and straight          # one displacement per straight pass
        # 1. side pass, eq 22
        e0, e1 = sx - r00, sy - r01
        a0 = e0 * d0 + e1 * d1
        a1 = (sx - rx) * d0 + (sy - ry) * d1
        lat = np.abs(d0 * e1 - d1 * e0)
        cross = straight and not was_passed and a0 > 0 and a1 <= 0 and lat > c and lat < side_range
        m = (1.0 if cross else 0.0) * amp * np.exp(-side_k * lat)
        sx = sx + m * d0
        sy = sy + m * d1
        npassed[b, i] = was_passed or cross
        # 2. release: the sphere follows a robot that moves away from it
        away = moving and ((sx - rx) * d0 + (sy - ry) * d1) < 0
        release = nattached[b, i] and away
        pend = amount if release else npending[b, i]
        follow = np.minimum(pend, size) if away else 0.0
        sx = sx + follow * d0
        sy = sy + follow * d1
        pend = pend - follow
        attached_i = nattached[b, i] and not release
        if release:
            any_release = True
            n_release += 1
        # 3. contact: carried along d in front of a moving robot, else pushed out along the line of centres
        e0, e1 = sx - rx, sy - ry
        along = e0 * d0 + e1 * d1
        lat = np.abs(d0 * e1 - d1 * e0)
        reach = np.sqrt(np.maximum(c * c - lat * lat, 0.0))
        carried = moving and along > -1e-12 and lat < c and along < reach * (1 - 1e-9)
        m = (1.0 if carried else 0.0) * (reach - along)
        sx = sx + m * d0
        sy = sy + m * d1
        e0, e1 = sx - rx, sy - ry
        dist = np.sqrt(e0 * e0 + e1 * e1)
        over = dist < c * (1 - 1e-9)
        if over:
            q = c / (dist if dist > 0 else 1.0)
            sx = rx + e0 * q
            sy = ry + e1 * q
        over = over or carried
        touching = over or (dist < c * (1 + 1e-9) and not away)
        any_over = any_over or over
        ns[b, 2 * i] = sx
        ns[b, 2 * i + 1] = sy
        nattached[b, i] = attached_i or touching
        npending[b, i] = 0.0 if touching else pend
        driven[i] = over or follow > 0       # moved by the robot this frame (contact or release)
    # 4. sphere-sphere: the sphere the robot did not drive gives way
    if n >= 2 and gap > 0:
        for i in range(n):
            for j in range(i + 1, n):
                sep0 = ns[b, 2 * j] - ns[b, 2 * i]
                sep1 = ns[b, 2 * j + 1] - ns[b, 2 * i + 1]
                dist = np.sqrt(sep0 * sep0 + sep1 * sep1)
                fix = gap - dist if dist < gap else 0.0
                if fix == 0.0:
                    continue
                q = dist if dist > 0 else 1.0
                v0, v1 = sep0 / q, sep1 / q
                move_j = not driven[j]
                fj = fix if move_j else 0.0
                fi = 0.0 if move_j else fix
                ns[b, 2 * j] += fj * v0
                ns[b, 2 * j + 1] += fj * v1
                ns[b, 2 * i] -= fi * v0
                ns[b, 2 * i + 1] -= fi * v1
    ncontact[b, 0] = any_over
    if moving:
        ndir[b, 0] = d0
        ndir[b, 1] = d1
    else:
        ndir[b, 0] = dir0
        ndir[b, 1] = dir1
    nreleases[b, 0] = rel_count + n_release
    nlast[b, 0] = amount if any_release else last


# --- the tracker ------------------------------------------------------------------------------------------
@jit
def standin_tracker_output(b, params, state, outputs):
    """``StandinTracker.output``: the estimates held in the state (the true values of the frame before)."""
    r, h, v, s, lost, k = state
    robot_est, heading_est, velocity_est, spheres_est, lost_out = outputs
    robot_est[b, 0] = r[b, 0]
    robot_est[b, 1] = r[b, 1]
    heading_est[b, 0] = h[b, 0]
    velocity_est[b, 0] = v[b, 0]
    velocity_est[b, 1] = v[b, 1]
    for i in range(spheres_est.shape[1]):
        spheres_est[b, i] = s[b, i]
    lost_out[b, 0] = lost[b, 0]


@jit
def standin_tracker_update(b, params, state, next_state, inputs, base, noise):
    """``StandinTracker.update``: ``lost`` outside the square field ``|x|, |y| ≤ half_width`` or in the
    blackout window ``[t0, t1)``; every sphere NaN in the sphere-loss window; ``t = (k + 1)·T``."""
    dt, half_width, blackout, black0, black1, sphere_loss, loss0, loss1 = params
    r, h, v, s, lost, k = state
    nr, nh, nv, ns, nlost, nk = next_state
    position, heading, spheres = inputs
    kk = k[b, 0] + 1
    t = kk * dt
    p0, p1 = position[b, 0], position[b, 1]
    out = np.abs(p0) > half_width or np.abs(p1) > half_width
    if blackout and black0 <= t < black1:
        out = True
    missing = sphere_loss and loss0 <= t < loss1
    for i in range(spheres.shape[1]):
        ns[b, i] = np.nan if missing else spheres[b, i]
    nv[b, 0] = (p0 - r[b, 0]) / dt
    nv[b, 1] = (p1 - r[b, 1]) / dt
    nr[b, 0] = p0
    nr[b, 1] = p1
    nh[b, 0] = heading[b, 0]
    nlost[b, 0] = out
    nk[b, 0] = kk
