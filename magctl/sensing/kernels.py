"""Kernels of the sensing blocks: the camera (positions mode), the blackout gate and the tracker (Kalman and
raw modes). They are these blocks' implementation, run by both engines.

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy reference (``tests/reference/sensing_blocks.py``,
which they are tested against; ``np.round`` is round-half-even,
``np.rint``; the tracker's ``F P Fᵀ`` is numpy's ``matmul``, whose 2 × 2 products are fused
multiply-adds). Imported only when a block's kernel is first asked for, so that numba stays out of the
import of ``magctl``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, overload

from magctl.core.philox import normal, uniform

OPTIONS = {"cache": True, "nogil": True, "inline": "always", "error_model": "numpy"}
jit = numba.njit(**OPTIONS)


@intrinsic
def fma(typingctx, a, b, c):
    """``a·b + c`` rounded once (LLVM's ``llvm.fma.f64``)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


# --- camera --------------------------------------------------------------------------------------------
@jit
def _quantise(x, pixel):
    """``s·round(x/s)``: to the nearest pixel centre, round half to even."""
    return pixel * np.rint(x / pixel)


@jit
def _measure(p, b, full, px, py, head, sph, key, k, mpos, mhead, msph, nmpos, nmhead, nmsph):
    """The positions-mode measurement of one trial: ``valid = full ∧ (u ≥ p_drop) ∧`` in view; positions
    ``s·round((x + s σ_px n)/s)``, heading ``arg e^{i(ψ + σ_θ n)}``; the held measurement when not valid.
    ``sph`` is read (row ``b``) before the new measurement is written, element by element."""
    n_sph, pixel, sig_pos, sig_head, p_drop, fov_w, fov_h = p
    valid = full and uniform(key, b, k, 0) >= p_drop and px >= 0 and px <= fov_w and py >= 0 and py <= fov_h
    if valid:
        nmpos[b, 0] = _quantise(px + sig_pos * normal(key, b, k, 0), pixel)
        nmpos[b, 1] = _quantise(py + sig_pos * normal(key, b, k, 1), pixel)
        x = head + sig_head * normal(key, b, k, 2)
        nmhead[b, 0] = math.atan2(math.sin(x), math.cos(x))
        for i in range(2 * n_sph):
            nmsph[b, i] = _quantise(sph[b, i] + sig_pos * normal(key, b, k, 3 + i), pixel)
    else:
        nmpos[b, 0] = mpos[b, 0]
        nmpos[b, 1] = mpos[b, 1]
        nmhead[b, 0] = mhead[b, 0]
        for i in range(2 * n_sph):
            nmsph[b, i] = msph[b, i]
    return valid


@jit
def camera_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``Camera.step`` without latency: the frame of this step measured now (stream position ``k``)."""
    k, mpos, mhead, msph = state
    nk, nmpos, nmhead, nmsph = next_state
    pos, head, sph = inputs
    opos, ohead, osph, ovalid = outputs
    valid = _measure(params, b, True, pos[b, 0], pos[b, 1], head[b, 0], sph, noise, k[b, 0],
                     mpos, mhead, msph, nmpos, nmhead, nmsph)
    opos[b, 0] = nmpos[b, 0]
    opos[b, 1] = nmpos[b, 1]
    ohead[b, 0] = nmhead[b, 0]
    for i in range(osph.shape[1]):
        osph[b, i] = nmsph[b, i]
    ovalid[b, 0] = valid
    nk[b, 0] = k[b, 0] + 1


@jit
def camera_output(b, params, state, outputs):
    """``Camera.output`` with latency: the measurement delivered now, held in the state."""
    mpos, mhead, msph, valid = state[-4], state[-3], state[-2], state[-1]
    opos, ohead, osph, ovalid = outputs
    opos[b, 0] = mpos[b, 0]
    opos[b, 1] = mpos[b, 1]
    ohead[b, 0] = mhead[b, 0]
    for i in range(osph.shape[1]):
        osph[b, i] = msph[b, i]
    ovalid[b, 0] = valid[b, 0]


def shift_pipeline(b, state, next_state, pos, head, sph):
    """The latency pipeline moved on by one frame (numba only: see its overload)."""


@overload(shift_pipeline, jit_options={"nogil": True, "error_model": "numpy"})
def _shift_pipeline(b, state, next_state, pos, head, sph):
    """``Camera.update``'s pipeline: frame ``j`` of the next state is frame ``j − 1`` of this one, frame 1 the
    input. The state is ``k``, then (``pos``, ``head``, ``sph``, ``full``) per frame from the oldest, then the
    measurement; the source is generated for the tuple's length, oldest frame first, so that each
    element is read before it is overwritten when the next state is the state itself."""
    frames = (len(state) - 5) // 4
    lines = ["def impl(b, state, next_state, pos, head, sph):"]
    for g in range(frames - 1):
        for f in range(4):
            dst, src = 1 + 4 * g + f, 1 + 4 * (g + 1) + f
            lines += [f"    for i in range(state[{src}].shape[1]):",
                      f"        next_state[{dst}][b, i] = state[{src}][b, i]"]
    last = 1 + 4 * (frames - 1)
    lines += [f"    next_state[{last}][b, 0] = pos[b, 0]", f"    next_state[{last}][b, 1] = pos[b, 1]",
              f"    next_state[{last + 1}][b, 0] = head[b, 0]",
              "    for i in range(sph.shape[1]):", f"        next_state[{last + 2}][b, i] = sph[b, i]",
              f"    next_state[{last + 3}][b, 0] = True", "    return None"]
    scope = {}
    exec("\n".join(lines), scope)  # noqa: S102 - source built above from integers only
    return scope["impl"]


@jit
def _copy_row(b, src, dst):
    for i in range(src.shape[1]):
        dst[b, i] = src[b, i]


@jit
def _measure_oldest(b, params, state, next_state, base, noise):
    """The frame now oldest in the next state measured at stream position ``k + 1``; ``k`` advanced."""
    k1 = state[0][b, 0] + 1
    spos, shead, ssph, sfull = next_state[1], next_state[2], next_state[3], next_state[4]
    valid = _measure(params, b, sfull[b, 0], spos[b, 0], spos[b, 1], shead[b, 0], ssph, noise, k1,
                     state[-4], state[-3], state[-2], next_state[-4], next_state[-3], next_state[-2])
    next_state[-1][b, 0] = valid
    next_state[0][b, 0] = k1


@jit
def camera_update_1(b, params, state, next_state, inputs, base, noise):
    """``Camera.update`` with a latency of 1 frame: the input is the frame delivered next (then measured at
    stream position ``k + 1``)."""
    pos, head, sph = inputs
    _copy_row(b, pos, next_state[1])
    _copy_row(b, head, next_state[2])
    _copy_row(b, sph, next_state[3])
    next_state[4][b, 0] = True
    _measure_oldest(b, params, state, next_state, base, noise)


@jit
def camera_update_2(b, params, state, next_state, inputs, base, noise):
    """``Camera.update`` with a latency of 2 frames: frame 2 ← frame 1 ← the input, then the new frame 2
    measured at stream position ``k + 1``."""
    pos, head, sph = inputs
    _copy_row(b, state[5], next_state[1])
    _copy_row(b, state[6], next_state[2])
    _copy_row(b, state[7], next_state[3])
    next_state[4][b, 0] = state[8][b, 0]
    _copy_row(b, pos, next_state[5])
    _copy_row(b, head, next_state[6])
    _copy_row(b, sph, next_state[7])
    next_state[8][b, 0] = True
    _measure_oldest(b, params, state, next_state, base, noise)


@jit
def camera_update(b, params, state, next_state, inputs, base, noise):
    """``Camera.update`` with any latency: the pipeline moves on (:func:`shift_pipeline`, a call), and the
    frame now oldest is measured at stream position ``k + 1`` (the measurement the next output delivers)."""
    pos, head, sph = inputs
    shift_pipeline(b, state, next_state, pos, head, sph)
    _measure_oldest(b, params, state, next_state, base, noise)


# --- blackout ------------------------------------------------------------------------------------------
@jit
def blackout_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``Blackout``: ``valid_out = valid ∧ ¬(t0 ≤ k·dt < t1)``."""
    windowed, t0, t1, dt = params
    k, = state
    nk, = next_state
    valid, = inputs
    out, = outputs
    t = k[b, 0] * dt
    out[b, 0] = False if (windowed and t0 <= t and t < t1) else valid[b, 0]
    nk[b, 0] = k[b, 0] + 1


# --- tracker -------------------------------------------------------------------------------------------
@jit
def tracker_step(b, params, state, next_state, inputs, outputs, base, noise):
    """``Tracker.step`` (raw and Kalman modes) of one trial.

    Per object ``m`` and axis ``a``: Kalman predict ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``, update with
    ``H = [1, 0]`` (``S = P⁻₀₀ + R``, ``K = P⁻[:, 0]/S``) when measured and initialised, start at
    ``[z, 0]``, ``diag(R, v₀²)`` on the first detection; raw mode takes ``z`` and the finite difference.
    Estimates ``p + d·T·v``; ``lost`` after ``max_coast`` frames without detection or before the first,
    when the estimates are held (``hold``) or NaN (``nan``).
    """
    kalman, nan_on_loss, n_sph, dt, r, f, q, v0sq, max_coast, ahead = params
    x, p, heading, init, missed, held_pos, held_sph = state
    nx, np_, nheading, ninit, nmissed, nheld_pos, nheld_sph = next_state
    zr, zh, zs, valid_in = inputs
    opos, ohead, ovel, osph, olost = outputs
    valid = valid_in[b, 0]
    was = init[b, 0]
    now = was or valid
    miss = 0 if valid else missed[b, 0] + 1
    lost = (not now) or miss > max_coast
    upd = valid and was
    start = valid and not was
    k0 = k1 = 0.0
    for m in range(1 + n_sph):
        o = 4 * m
        p00, p01, p10, p11 = p[b, o], p[b, o + 1], p[b, o + 2], p[b, o + 3]
        if kalman:
            # F P Fᵀ + Q, with matmul's fused products
            fp00 = fma(f[0, 1], p10, f[0, 0] * p00)
            fp01 = fma(f[0, 1], p11, f[0, 0] * p01)
            fp10 = fma(f[1, 1], p10, f[1, 0] * p00)
            fp11 = fma(f[1, 1], p11, f[1, 0] * p01)
            q00, q01, q10, q11 = q[m, 0, 0], q[m, 0, 1], q[m, 1, 0], q[m, 1, 1]
            pp00 = fma(fp01, f[0, 1], fp00 * f[0, 0]) + q00
            pp01 = fma(fp01, f[1, 1], fp00 * f[1, 0]) + q01
            pp10 = fma(fp11, f[0, 1], fp10 * f[0, 0]) + q10
            pp11 = fma(fp11, f[1, 1], fp10 * f[1, 0]) + q11
            s = pp00 + r
            k0 = pp00 / s
            k1 = pp10 / s
            if upd:
                n00, n01, n10, n11 = pp00 - k0 * pp00, pp01 - k0 * pp01, pp10 - k1 * pp00, pp11 - k1 * pp01
            elif start:
                n00, n01, n10, n11 = r, 0.0, 0.0, v0sq
            elif was:
                n00, n01, n10, n11 = pp00, pp01, pp10, pp11
            else:
                n00, n01, n10, n11 = p00, p01, p10, p11
        else:
            n00, n01, n10, n11 = p00, p01, p10, p11
        np_[b, o], np_[b, o + 1], np_[b, o + 2], np_[b, o + 3] = n00, n01, n10, n11
        for a in range(2):
            j = o + 2 * a
            pos, vel = x[b, j], x[b, j + 1]
            z = zr[b, a] if m == 0 else zs[b, 2 * (m - 1) + a]
            if kalman:
                xp0 = f[0, 0] * pos + f[0, 1] * vel
                xp1 = f[1, 0] * pos + f[1, 1] * vel
                if upd:
                    innov = z - xp0
                    npos, nvel = xp0 + k0 * innov, xp1 + k1 * innov
                elif start:
                    npos, nvel = z, 0.0
                elif was:
                    npos, nvel = xp0, xp1
                else:
                    npos, nvel = pos, vel
            else:
                nvel = (z - pos) / dt if upd else 0.0
                npos = z if valid else pos
            nx[b, j], nx[b, j + 1] = npos, nvel
            est = npos + ahead * nvel
            if m == 0:
                v = 0.0 if lost else nvel
                if lost and not nan_on_loss:
                    est = held_pos[b, a]
                if not nan_on_loss:
                    nheld_pos[b, a] = est
                opos[b, a] = np.nan if (lost and nan_on_loss) else est
                ovel[b, a] = np.nan if (lost and nan_on_loss) else v
            else:
                i = 2 * (m - 1) + a
                if lost and not nan_on_loss:
                    est = held_sph[b, i]
                if not nan_on_loss:
                    nheld_sph[b, i] = est
                osph[b, i] = np.nan if (lost and nan_on_loss) else est
    if nan_on_loss:  # the held estimates are kept as they are
        for a in range(2):
            nheld_pos[b, a] = held_pos[b, a]
        for i in range(2 * n_sph):
            nheld_sph[b, i] = held_sph[b, i]
    hd = zh[b, 0] if valid else heading[b, 0]
    nheading[b, 0] = hd
    ohead[b, 0] = np.nan if (lost and nan_on_loss) else hd
    ninit[b, 0] = now
    nmissed[b, 0] = miss
    olost[b, 0] = lost
