"""Kernels of the plant blocks: the coil actuator, the drive, the stick-slip robot and the fused
drive → coils → robot block. They are the blocks' only implementation, run by both engines (the
interpreted one through :mod:`magctl.core.kernel_driver`).

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy reference (``tests/reference/plant_blocks.py``;
sums in the order numpy's ``einsum`` makes them; ``np.maximum``/``np.minimum`` with their NaN
propagation). Transcendental functions call libm, whose last bit may differ from numpy's vectorised
loops, so results agree to rounding, not always to the bit. Imported when a block first runs, so that
numba stays out of the import of ``magctl``.
"""

from __future__ import annotations

import math

import numba

from magctl.core.philox import normal

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")


@jit
def nmax(a, b):
    """``np.maximum(a, b)`` of two floats (NaN propagates)."""
    return a if (a >= b or a != a) else b


@jit
def nmin(a, b):
    """``np.minimum(a, b)`` of two floats (NaN propagates)."""
    return a if (a <= b or a != a) else b


# --- coils ---------------------------------------------------------------------------------------------
@jit
def coil_field(cp, b, bs0, bs1, bosc, freq_cmd, i, ni, cur, write_cur):
    """The coil actuator's allocation, limits and RL step for one trial: minimum-norm allocation ``i_s = A⁺ b``, static
    scaling to ``I_max``, oscillation share ``s_osc`` of what current and voltage are left, voltage clip,
    frame-average currents ``ī = i_s + (i − i_s)·(τ/h)(1 − e^{−h/τ})`` (written to ``cur`` when
    ``write_cur``) and next currents ``i_s + (i − i_s)·e^{−h/τ}`` (to ``ni``).

    The static scaling is decided per trial (a trial is scaled when one of its coils exceeds its limit);
    the numpy reference decides whether to scale over the batch, which differs only when a trial sits within
    rounding of a limit. Returns the delivered ``b_x, b_y``, ``b_osc``, frequency and ``saturated``.
    """
    (per_xy, clamp, imax, inv_imax, zc, imax_z, vmax_z, r_z, r2, two_pi_l, inv_pz,
     vclip, vmax_over_r, avg_w, decay, a_xy) = cp
    n = clamp.shape[0]
    # step 1-2: static currents and their scaling
    ratio = 0.0
    over = False
    for c in range(n):
        a = abs((bs0 * per_xy[0, c] + bs1 * per_xy[1, c]) + clamp[c])
        ratio = nmax(ratio, a * inv_imax[c]) if c else a * inv_imax[c]
        if a > imax[c]:
            over = True
    scale = 1.0
    if over:
        scale = 1.0 / nmax(ratio, 1.0)
    # oscillation: s = min(1, min_c cap_c / |b_osc|) over the coils that carry it
    freq = nmax(freq_cmd, 0.0)
    cap_min = 0.0
    for q in range(zc.shape[0]):
        c = zc[q]
        az = abs((bs0 * per_xy[0, c] + bs1 * per_xy[1, c]) + clamp[c])
        if over:
            az = az * scale
        w = freq * two_pi_l[q]
        z = math.sqrt(r2[q] + w * w)
        cap = nmin(imax_z[q] - az, (vmax_z[q] - r_z[q] * az) / z)
        cap = cap * inv_pz[q]
        cap_min = nmin(cap_min, cap) if q else cap
    s_osc = nmin(cap_min / nmax(abs(bosc), 1e-300), 1.0)
    # step 3: frame-average and next currents, delivered in-plane field (sum over coils in order)
    bd0 = 0.0
    bd1 = 0.0
    for c in range(n):
        i_s = (bs0 * per_xy[0, c] + bs1 * per_xy[1, c]) + clamp[c]
        if over:
            i_s = i_s * scale
        if vclip:
            i_s = nmin(nmax(i_s, -vmax_over_r[c]), vmax_over_r[c])
        i0 = i[b, c]
        i_avg = i_s + (i0 - i_s) * avg_w[c]
        bd0 += i_avg * a_xy[c, 0]
        bd1 += i_avg * a_xy[c, 1]
        if write_cur:
            cur[b, c] = i_avg
        ni[b, c] = i_s + (i0 - i_s) * decay[c]
    sat = s_osc < 1.0 - 1e-12
    if over and scale < 1.0:
        sat = True
    return bd0, bd1, bosc * s_osc, freq, sat


@jit
def coils_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``CoilActuator.step``: outputs ``currents``, delivered field and ``saturated``; next coil currents."""
    i, = state
    ni, = next_state
    bs, bo, fr = inputs
    cur, bsd, bod, frd, sat = outputs
    bd0, bd1, bosc, freq, s = coil_field(params, b, bs[b, 0], bs[b, 1], bo[b, 0], fr[b, 0], i, ni, cur, True)
    bsd[b, 0] = bd0
    bsd[b, 1] = bd1
    bod[b, 0] = bosc
    frd[b, 0] = freq
    sat[b, 0] = s


# --- drive ---------------------------------------------------------------------------------------------
@jit
def interp(x, xp, fp):
    """``np.interp(x, xp, fp)`` for one ``x`` (numpy's algorithm: the last ``j`` with ``xp[j] ≤ x``,
    ``fp[j]`` where ``x`` hits a node, else ``slope·(x − xp[j]) + fp[j]``)."""
    n = xp.shape[0]
    if x != x:
        return x
    if x > xp[n - 1]:
        return fp[n - 1]
    if x < xp[0]:
        return fp[0]
    lo, hi = 0, n
    while lo < hi:
        mid = lo + ((hi - lo) >> 1)
        if x >= xp[mid]:
            lo = mid + 1
        else:
            hi = mid
    j = lo - 1
    if j == n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    y = slope * (x - xp[j]) + fp[j]
    if y != y:
        y = slope * (x - xp[j + 1]) + fp[j + 1]
        if y != y and fp[j] == fp[j + 1]:
            y = fp[j]
    return y


@jit
def drive_command(dp, speed, heading):
    """``Drive.output``: ``f = v⁻¹(clip(speed, 0, v_max))`` (0 at zero speed), ``b_static = B_0 (cos ψ, sin ψ)``,
    ``b_osc`` nominal while moving. Returns ``b_x, b_y, b_osc, f``."""
    v_table, f_table, max_speed, static_field, osc_field = dp
    sp = nmin(nmax(speed, 0.0), max_speed)
    f = interp(sp, v_table, f_table)
    on = sp > 0.0
    f = f * (1.0 if on else 0.0)
    return (math.cos(heading) * static_field, math.sin(heading) * static_field,
            (1.0 if on else 0.0) * osc_field, f)


@jit
def drive_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``Drive.output`` (stateless)."""
    sp, psi = inputs
    bs, bo, fr = outputs
    bx, by, bosc, f = drive_command(params, sp[b, 0], psi[b, 0])
    bs[b, 0] = bx
    bs[b, 1] = by
    bo[b, 0] = bosc
    fr[b, 0] = f


# --- stick-slip robot ----------------------------------------------------------------------------------
@jit
def robot_advance(rp, bs0, bs1, bosc, freq_in, psi, px, py, noisy, n):
    """``StickSlipRobot.update`` of one trial: heading by the exact solution ``tan(e/2) = tan(e₀/2) e^{−t/τ_ψ}``
    at the frame's middle and end, speed ``v = f·η ℓ [cos θ_0 − cos θ_a]₊`` (times ``max(0, 1 + c_v n)``
    when ``noisy``), displacement by Simpson's rule (numpy's einsum sums the three terms as
    ``(w₀c₀ + w₂c₂) + w₁c₁``), heading wrapped to [−π, π). Returns ``pos, ψ, v̄, θ̄``."""
    dt, half_rate, pitch_c, cos0, eta_l, simpson, cv = rp
    bmag = math.hypot(bs0, bs1)
    psi_b = math.atan2(bs1, bs0)
    t0 = math.tan(0.5 * (psi - psi_b))
    k = math.exp(half_rate * bmag)
    tk = t0 * k
    p1 = psi_b + 2.0 * math.atan(tk)
    p2 = psi_b + 2.0 * math.atan(tk * k)
    freq = nmax(freq_in, 0.0)
    theta = math.atan2(abs(bosc), bmag) * bmag / nmax(math.hypot(bmag, pitch_c * freq), 1e-300)
    v = freq * nmax(cos0 - math.cos(theta), 0.0)
    v = v * eta_l
    if noisy:
        v = v * nmax(1.0 + cv * n, 0.0)
    vx = (math.cos(psi) * simpson[0] + math.cos(p2) * simpson[2]) + math.cos(p1) * simpson[1]
    vy = (math.sin(psi) * simpson[0] + math.sin(p2) * simpson[2]) + math.sin(p1) * simpson[1]
    vx = vx * v
    vy = vy * v
    psi1 = (p2 + math.pi) % (2.0 * math.pi) - math.pi   # np.remainder: the sign of the divisor
    return px + vx * dt, py + vy * dt, psi1, vx, vy, theta * (2.0 / math.pi)


@jit
def _pose_out(b, pos, psi, vel, tilt, op, oh, ov, ot):
    """The robot's outputs from its state: position, heading, velocity, tilt."""
    op[b, 0] = pos[b, 0]
    op[b, 1] = pos[b, 1]
    oh[b, 0] = psi[b, 0]
    ov[b, 0] = vel[b, 0]
    ov[b, 1] = vel[b, 1]
    ot[b, 0] = tilt[b, 0]


@jit
def robot_output(b, params, state, outputs):
    """``StickSlipRobot.output``: the pose, velocity and tilt held in the state."""
    pos, psi, vel, tilt, k = state
    op, oh, ov, ot = outputs
    _pose_out(b, pos, psi, vel, tilt, op, oh, ov, ot)


@jit
def _robot_write(b, state, next_state, r):
    pos, psi, vel, tilt, k = state
    npos, npsi, nvel, ntilt, nk = next_state
    npos[b, 0], npos[b, 1], npsi[b, 0], nvel[b, 0], nvel[b, 1], ntilt[b, 0] = r
    nk[b, 0] = k[b, 0] + 1


@jit
def robot_update(b, params, state, next_state, inputs, base, noise):
    """``StickSlipRobot.update`` without step variability."""
    pos, psi, vel, tilt, k = state
    bs, bo, fr = inputs
    r = robot_advance(params, bs[b, 0], bs[b, 1], bo[b, 0], fr[b, 0], psi[b, 0], pos[b, 0], pos[b, 1], False, 0.0)
    _robot_write(b, state, next_state, r)


@jit
def robot_update_noisy(b, params, state, next_state, inputs, base, noise):
    """``StickSlipRobot.update`` with the step variation ``n ~ N(0, 1)`` of stream position ``k``."""
    pos, psi, vel, tilt, k = state
    bs, bo, fr = inputs
    n = normal(noise, b, k[b, 0], 0)
    r = robot_advance(params, bs[b, 0], bs[b, 1], bo[b, 0], fr[b, 0], psi[b, 0], pos[b, 0], pos[b, 1], True, n)
    _robot_write(b, state, next_state, r)


# --- drive → coils → robot fused -----------------------------------------------------------------------
@jit
def actuated_output(b, params, state, outputs):
    """``ActuatedRobot.output``: the robot's outputs and the previous frame's ``saturated``."""
    i, pos, psi, vel, tilt, k, sat = state
    op, oh, ov, ot, osat = outputs
    _pose_out(b, pos, psi, vel, tilt, op, oh, ov, ot)
    osat[b, 0] = sat[b, 0]


@jit
def _actuated(b, params, state, next_state, inputs, noisy, n):
    i, pos, psi, vel, tilt, k, sat = state
    ni, npos, npsi, nvel, ntilt, nk, nsat = next_state
    sp, hd = inputs
    dp = params[0:5]
    cp = params[5:21]
    rp = params[21:28]
    bx, by, bosc, f = drive_command(dp, sp[b, 0], hd[b, 0])
    bd0, bd1, bod, frd, s = coil_field(cp, b, bx, by, bosc, f, i, ni, i, False)
    r = robot_advance(rp, bd0, bd1, bod, frd, psi[b, 0], pos[b, 0], pos[b, 1], noisy, n)
    npos[b, 0], npos[b, 1], npsi[b, 0], nvel[b, 0], nvel[b, 1], ntilt[b, 0] = r
    nk[b, 0] = k[b, 0] + 1
    nsat[b, 0] = s


@jit
def actuated_update(b, params, state, next_state, inputs, base, noise):
    """``ActuatedRobot.update``: drive command, coil field and RL step, robot step (no step variability)."""
    _actuated(b, params, state, next_state, inputs, False, 0.0)


@jit
def actuated_update_noisy(b, params, state, next_state, inputs, base, noise):
    """``ActuatedRobot.update`` with the robot's step variation at stream position ``robot.k``."""
    k = state[5]
    _actuated(b, params, state, next_state, inputs, True, normal(noise, b, k[b, 0], 0))
