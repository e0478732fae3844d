"""Compiled kernels of the core blocks (linear blocks, norm saturation, Gaussian noise).

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy form. Imported only when a diagram is
compiled, so that numba stays out of the import of ``magctl``.
"""

from __future__ import annotations

import math

import numba

from magctl.core.philox import normal_pair

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")


@jit
def constant_output(b, params, state, outputs):
    y, = state
    out, = outputs
    for i in range(out.shape[1]):
        out[b, i] = y[b, i]


@jit
def no_update(b, params, state, next_state, inputs, base, noise):
    for j in range(len(state)):
        for i in range(state[j].shape[1]):
            next_state[j][b, i] = state[j][b, i]


@jit
def gain_scalar_step(b, params, state, next_state, inputs, outputs, base, noise):
    k, = params
    u, = inputs
    y, = outputs
    for i in range(y.shape[1]):
        y[b, i] = u[b, i] * k


@jit
def gain_matrix_step(b, params, state, next_state, inputs, outputs, base, noise):
    k, = params                      # (m, n): y = K u, summed in the order of u's elements
    u, = inputs
    y, = outputs
    for r in range(k.shape[0]):
        acc = 0.0
        for c in range(k.shape[1]):
            acc += u[b, c] * k[r, c]
        y[b, r] = acc


@jit
def sum_step(b, params, state, next_state, inputs, outputs, base, noise):
    signs, = params
    y, = outputs
    for i in range(y.shape[1]):
        acc = inputs[0][b, i] if signs[0] > 0 else -inputs[0][b, i]
        for j in range(1, len(inputs)):
            if signs[j] > 0:
                acc = acc + inputs[j][b, i]
            else:
                acc = acc - inputs[j][b, i]
        y[b, i] = acc


@jit
def delay_output(b, params, state, outputs):
    y, = outputs
    for i in range(y.shape[1]):
        y[b, i] = state[0][b, i]


@jit
def delay_update(b, params, state, next_state, inputs, base, noise):
    u, = inputs
    d = len(state)
    for j in range(d - 1):
        for i in range(u.shape[1]):
            next_state[j][b, i] = state[j + 1][b, i]
    for i in range(u.shape[1]):
        next_state[d - 1][b, i] = u[b, i]


@jit
def integrator_update(b, params, state, next_state, inputs, base, noise):
    gain_dt, = params
    x, = state
    nx, = next_state
    u, = inputs
    for i in range(x.shape[1]):
        nx[b, i] = x[b, i] + gain_dt * u[b, i]


@jit
def pi_step(b, params, state, next_state, inputs, outputs, base, noise):
    kp, ki, dt, limit, mode, saturate = params   # mode: 0 no limit, 1 norm, 2 element-wise
    integral, = state
    nxt, = next_state
    e, = inputs
    u, sat = outputs
    n = e.shape[1]
    over = False
    mag = 0.0
    if mode == 1:
        acc = 0.0
        for i in range(n):
            r = kp * e[b, i] + ki * integral[b, i]
            acc += r * r
        mag = math.sqrt(acc)      # not hypot: no overflow is possible here, and sqrt is several times faster
        over = mag > limit
    elif mode == 2:
        for i in range(n):
            mag = max(mag, abs(kp * e[b, i] + ki * integral[b, i]))
        over = mag > limit
    scale = limit / mag if over else 1.0
    for i in range(n):
        raw = kp * e[b, i] + ki * integral[b, i]
        if over and saturate:
            raw = raw * scale if mode == 1 else min(max(raw, -limit), limit)
        u[b, i] = raw
        nxt[b, i] = integral[b, i] + (dt * e[b, i]) * (0.0 if over else 1.0)
    sat[b, 0] = over


@jit
def state_space_output(b, params, state, outputs):
    a, bm, c, d = params
    x, = state
    y, = outputs
    for r in range(c.shape[0]):
        acc = 0.0
        for j in range(c.shape[1]):
            acc += x[b, j] * c[r, j]
        y[b, r] = acc


@jit
def state_space_update(b, params, state, next_state, inputs, base, noise):
    a, bm, c, d = params
    x, = state
    nx, = next_state
    u, = inputs
    for r in range(a.shape[0]):
        acc = 0.0
        for j in range(a.shape[1]):
            acc += x[b, j] * a[r, j]
        acc2 = 0.0
        for j in range(bm.shape[1]):
            acc2 += u[b, j] * bm[r, j]
        nx[b, r] = acc + acc2


@jit
def state_space_step(b, params, state, next_state, inputs, outputs, base, noise):
    a, bm, c, d = params
    x, = state
    nx, = next_state
    u, = inputs
    y, = outputs
    for r in range(c.shape[0]):
        acc = 0.0
        for j in range(c.shape[1]):
            acc += x[b, j] * c[r, j]
        acc2 = 0.0
        for j in range(d.shape[1]):
            acc2 += u[b, j] * d[r, j]
        y[b, r] = acc + acc2
    state_space_update(b, params, state, next_state, inputs, base, noise)


@jit
def norm_saturation_step(b, params, state, next_state, inputs, outputs, base, noise):
    limit, = params
    u, = inputs
    y, sat = outputs
    n = u.shape[1]
    acc = 0.0
    for i in range(n):
        acc += u[b, i] * u[b, i]
    mag = math.sqrt(acc)
    over = mag > limit
    scale = limit / mag if over else 1.0
    for i in range(n):
        y[b, i] = u[b, i] * scale if over else u[b, i]
    sat[b, 0] = over


@jit
def gaussian_noise_step(b, params, state, next_state, inputs, outputs, base, noise):
    sigma, = params
    k, = state
    nk, = next_state
    u, = inputs
    y, = outputs
    n = y.shape[1]
    for j in range((n + 1) // 2):
        z0, z1 = normal_pair(noise, b, k[b, 0], j)
        y[b, 2 * j] = u[b, 2 * j] + sigma * z0
        if 2 * j + 1 < n:
            y[b, 2 * j + 1] = u[b, 2 * j + 1] + sigma * z1
    nk[b, 0] = k[b, 0] + 1
