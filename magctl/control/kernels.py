"""Compiled kernels of the controller blocks: the PI servo, the learning laws, the go-to status and the patrol.

Each function runs one trial ``b`` in the convention of :mod:`magctl.core.kernel`, with the same
floating-point operations per element as the block's numpy reference in ``tests/reference``
(``np.minimum``/``np.maximum`` propagate NaN, as :func:`nan_min` / :func:`nan_max` do here). The learning laws
are the eq 13/18 integrator (:class:`~magctl.control.learning.LearningLaw`), the side push's curve-learning law
(:class:`~magctl.control.curve_learning.CurveLearningLaw`, an iterated EKF over fixed-size state) and the front
push's release-model law (:class:`~magctl.control.release_model.ReleasePolicyLaw`, a nearest-neighbour policy);
the push tasks call the same functions from :mod:`magctl.control.push.kernels`. Imported only when a diagram is
compiled, so that numba stays out of the import of ``magctl``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from magctl.control.status import Status

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")

RUNNING, CONVERGED, TRACKING_LOST = int(Status.RUNNING), int(Status.CONVERGED), int(Status.TRACKING_LOST)
"""Status codes (:class:`magctl.control.status.Status`)."""

COST_RISE_TOL = 1e-9
"""A Gauss–Newton step of the curve law's update (:func:`curve_update`) counts as not raising ``J`` when it raises it
by less than this fraction of ``1 + J``: far above the rounding of ``J`` (~1e-16; near the mode successive steps
change ``J`` by that much either way, and numpy's and libm's ``exp`` differ in the last bit), far below any rise the
halving guards against. Without it a step is halved or not by rounding noise, and the kernel's estimates and a numpy
form's part by ~1e-6."""
HALVINGS = 30
"""Most halvings of one Gauss–Newton step (after them the step is taken as it is)."""



class CurveParams(NamedTuple):
    """The curve-learning law's parameters as its kernels read them, by name
    (:meth:`~magctl.control.curve_learning.CurveLearningLaw.kernel_params`)."""

    reference_gap: float
    """``g_ref`` (m), the gap the estimate's ``x`` is measured from."""
    pass_var: float
    """``σ_pass²``, the pass-to-pass scatter of ``D_s`` (relative)."""
    measure_var: float
    """``σ_meas²`` (m²), the measurement noise of a displacement."""
    b_min: float
    """The floor of the estimated decay rate ``b``."""
    exp_a0: float
    """The prior's ``exp(a₀)`` (m), which the output ``y`` is taken from."""
    drift: np.ndarray
    """The drift covariance ``Q`` per attempt, 3×3 row-major (9,)."""


def no_curve() -> CurveParams:
    """The curve law's parameters for a task without it (never read)."""
    return CurveParams(0.0, 0.0, 0.0, 0.0, 0.0, np.zeros(9))


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


# --- curve-learning law (magctl.control.curve_learning) -----------------------------------------------------
@jit
def cholesky3(p00, p10, p11, p20, p21, p22):
    """The lower Cholesky factor ``L`` of a symmetric positive-definite 3×3 matrix from its lower triangle, as
    ``(l00, l10, l11, l20, l21, l22)``."""
    l00 = math.sqrt(p00)
    l10 = p10 / l00
    l20 = p20 / l00
    l11 = math.sqrt(p11 - l10 * l10)
    l21 = (p21 - l20 * l10) / l11
    l22 = math.sqrt(p22 - l20 * l20 - l21 * l21)
    return l00, l10, l11, l20, l21, l22


@jit
def quadratic3(chol, d0, d1, d2):
    """``dᵀ P⁻¹ d = |L⁻¹ d|²`` with ``chol`` = :func:`cholesky3` of ``P``, by forward substitution (a sum of
    squares: no cancellation, whatever the conditioning of ``P``)."""
    l00, l10, l11, l20, l21, l22 = chol
    y0 = d0 / l00
    y1 = (d1 - l10 * y0) / l11
    y2 = (d2 - l20 * y0 - l21 * y1) / l22
    return y0 * y0 + y1 * y1 + y2 * y2


@jit
def curve_cost(t0, t1, t2, th0, th1, th2, chol, z, x, r):
    """The negative log posterior ``J(θ)`` of one pass: the prior term and ``(z − h(θ))²/R``."""
    miss = z - (math.exp(t0 - t1 * x) - t2)
    return quadratic3(chol, t0 - th0, t1 - th1, t2 - th2) + miss * miss / r


@jit
def curve_update(b, cp, iterations, theta, cov, ntheta, ncov, gap, z):
    """:class:`~magctl.control.curve_learning.CurveLearningLaw`'s update for trial ``b``: the iterated EKF step
    from the pass ``(D_g, D_s,act)`` on ``D_s = exp(a − b·x) − c`` (docs/push-control.md §6, the side push's
    replacement for eq 17–18), written to ``ntheta``, ``ncov`` (which may be ``theta``, ``cov``: everything is read
    first). ``cov`` is the 3×3 covariance row-major."""
    gref = cp.reference_gap
    x = (gap - gref) / gref
    p = ((cov[b, 0] + cp.drift[0], cov[b, 1] + cp.drift[1], cov[b, 2] + cp.drift[2]),
         (cov[b, 3] + cp.drift[3], cov[b, 4] + cp.drift[4], cov[b, 5] + cp.drift[5]),
         (cov[b, 6] + cp.drift[6], cov[b, 7] + cp.drift[7], cov[b, 8] + cp.drift[8]))
    chol = cholesky3(p[0][0], p[1][0], p[1][1], p[2][0], p[2][1], p[2][2])
    th0 = theta[b, 0]
    th1 = theta[b, 1]
    th2 = theta[b, 2]
    e0 = math.exp(th0 - th1 * x)
    r = cp.pass_var * e0 * e0 + cp.measure_var
    it0, it1, it2 = th0, th1, th2
    j_it = curve_cost(it0, it1, it2, th0, th1, th2, chol, z, x, r)
    h = (0.0, 0.0, -1.0)
    g = (0.0, 0.0, 0.0)
    for _ in range(iterations):
        e = math.exp(it0 - it1 * x)
        h = (e, -x * e, -1.0)
        ph0 = p[0][0] * h[0] + p[0][1] * h[1] + p[0][2] * h[2]
        ph1 = p[1][0] * h[0] + p[1][1] * h[1] + p[1][2] * h[2]
        ph2 = p[2][0] * h[0] + p[2][1] * h[1] + p[2][2] * h[2]
        s = h[0] * ph0 + h[1] * ph1 + h[2] * ph2 + r
        g = (ph0 / s, ph1 / s, ph2 / s)
        innovation = z - (e - it2) - (h[0] * (th0 - it0) + h[1] * (th1 - it1) + h[2] * (th2 - it2))
        s0 = th0 + g[0] * innovation - it0
        s1 = th1 + g[1] * innovation - it1
        s2 = th2 + g[2] * innovation - it2
        t0 = it0 + s0
        t1 = it1 + s1
        t2 = it2 + s2
        j_trial = curve_cost(t0, t1, t2, th0, th1, th2, chol, z, x, r)
        for _halving in range(HALVINGS):
            if j_trial <= j_it + COST_RISE_TOL * (1.0 + j_it):
                break
            s0 = 0.5 * s0
            s1 = 0.5 * s1
            s2 = 0.5 * s2
            t0 = it0 + s0
            t1 = it1 + s1
            t2 = it2 + s2
            j_trial = curve_cost(t0, t1, t2, th0, th1, th2, chol, z, x, r)
        it0, it1, it2 = t0, t1, t2
        j_it = nan_min(j_trial, j_it)
    # Joseph form at the last linearisation: (I − K·H) P⁻ (I − K·H)ᵀ + R·K·Kᵀ
    ikh = (((1.0 - g[0] * h[0]), (0.0 - g[0] * h[1]), (0.0 - g[0] * h[2])),
           ((0.0 - g[1] * h[0]), (1.0 - g[1] * h[1]), (0.0 - g[1] * h[2])),
           ((0.0 - g[2] * h[0]), (0.0 - g[2] * h[1]), (1.0 - g[2] * h[2])))
    for i in range(3):
        a0 = ikh[i][0] * p[0][0] + ikh[i][1] * p[1][0] + ikh[i][2] * p[2][0]
        a1 = ikh[i][0] * p[0][1] + ikh[i][1] * p[1][1] + ikh[i][2] * p[2][1]
        a2 = ikh[i][0] * p[0][2] + ikh[i][1] * p[1][2] + ikh[i][2] * p[2][2]
        for m in range(3):
            ncov[b, 3 * i + m] = a0 * ikh[m][0] + a1 * ikh[m][1] + a2 * ikh[m][2] + r * g[i] * g[m]
    ntheta[b, 0] = it0
    ntheta[b, 1] = nan_max(it1, cp.b_min)
    ntheta[b, 2] = it2


@jit
def curve_displacement(theta, b, cp, gap):
    """:meth:`CurveLearningLaw.displacement`: the estimated attempt ``exp(a − b·x) − c`` at ``gap``."""
    gref = cp.reference_gap
    return math.exp(theta[b, 0] - theta[b, 1] * (gap - gref) / gref) - theta[b, 2]


@jit
def curve_gap(theta, b, cp, d_des, min_gap):
    """:meth:`CurveLearningLaw.gap`: the gap the estimate says gives ``d_des``, not below ``min_gap``."""
    a = theta[b, 0]
    want = d_des + theta[b, 2]
    floor = 0.01 * math.exp(a)
    g = cp.reference_gap * (1.0 + (a - math.log(nan_max(want, floor))) / theta[b, 1])
    return nan_max(g, min_gap)


batch_jit = numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
"""A loop over the trials, called from Python (the law's queries of its estimate)."""


@batch_jit
def curve_displacements(theta, cp, gap, out):
    """:meth:`CurveLearningLaw.displacement`: :func:`curve_displacement` of every trial at its ``gap[b]``, into
    ``out``."""
    for b in range(theta.shape[0]):
        out[b] = curve_displacement(theta, b, cp, gap[b])


@batch_jit
def curve_gaps(theta, cp, d_des, min_gap, out):
    """:meth:`CurveLearningLaw.gap`: :func:`curve_gap` of every trial for its ``d_des[b]``, into ``out``."""
    for b in range(theta.shape[0]):
        out[b] = curve_gap(theta, b, cp, d_des[b], min_gap)


@jit
def curve_correction(theta, b, cp):
    """The law's output ``y``: the estimate's displacement at ``g_ref`` minus the prior's."""
    return math.exp(theta[b, 0]) - cp.exp_a0


@jit
def curve_output(b, params, state, outputs):
    """:class:`~magctl.control.curve_learning.CurveLearningLaw`: ``y = exp(a) − exp(a₀)``."""
    cp, iterations = params
    theta, cov = state
    y, = outputs
    y[b, 0] = curve_correction(theta, b, cp)


@jit
def curve_update_step(b, params, state, next_state, inputs, base, noise):
    """:class:`~magctl.control.curve_learning.CurveLearningLaw`: one iterated EKF step per attempt."""
    cp, iterations = params
    theta, cov = state
    ntheta, ncov = next_state
    gap, z = inputs
    curve_update(b, cp, iterations, theta, cov, ntheta, ncov, gap[b, 0], z[b, 0])


# --- release-model law (magctl.control.release_model) -------------------------------------------------------
@jit
def _d2(xs0, xs1, pos, q0, q1):
    """Squared scaled distance of logged attempt ``pos`` from the query, as the tree computes it."""
    d0 = xs0[pos] - q0
    d1 = xs1[pos] - q1
    return d0 * d0 + d1 * d1


@jit
def _before(d2a, ra, d2b, rb):
    """``(d², row)`` a comes before b: nearer, or as near and earlier in the map."""
    return d2a < d2b or (d2a == d2b and ra < rb)


@jit
def release_nearest(b, xs0, xs1, srow, nb, q0, q1):
    """The ``k = nb.shape[1]`` logged later attempts nearest ``(q0, q1)`` (scaled), nearest first, ties to the
    earlier map row (:class:`~magctl.control.release_model.ReleasePolicy`), as positions in the ``xs0``-sorted
    table, in ``nb[b]``.

    Walks outwards from the query's place in the sorted first coordinate and stops a side once its first-coordinate
    distance alone exceeds the k-th nearest's distance (no later point on that side can be nearer)."""
    k = nb.shape[1]
    n = xs0.shape[0]
    lo = 0
    hi = n
    while lo < hi:  # first position with xs0 >= q0
        mid = (lo + hi) // 2
        if xs0[mid] < q0:
            lo = mid + 1
        else:
            hi = mid
    left = lo - 1
    right = lo
    m = 0
    while left >= 0 or right < n:
        if m == k:
            worst = _d2(xs0, xs1, nb[b, k - 1], q0, q1)
            if left >= 0:
                dl = xs0[left] - q0
                if dl * dl > worst:
                    left = -1
            if right < n:
                dr = xs0[right] - q0
                if dr * dr > worst:
                    right = n
            if left < 0 and right >= n:
                break
        if left >= 0 and (right >= n or q0 - xs0[left] <= xs0[right] - q0):
            pos = left
            left -= 1
        else:
            pos = right
            right += 1
        d2 = _d2(xs0, xs1, pos, q0, q1)
        row = srow[pos]
        if m == k:
            last = nb[b, k - 1]
            if not _before(d2, row, _d2(xs0, xs1, last, q0, q1), srow[last]):
                continue
            j = k - 1
        else:
            j = m
            m += 1
        while j > 0 and _before(d2, row, _d2(xs0, xs1, nb[b, j - 1], q0, q1), srow[nb[b, j - 1]]):
            nb[b, j] = nb[b, j - 1]
            j -= 1
        nb[b, j] = pos


@jit
def release_choose(b, scale, deltas, xs0, xs1, srow, succ, nb, d, previous):
    """The release-model controller's choice for one trial: the index of the candidate ``δ`` whose ``k`` nearest logged
    later attempts at ``(d + δ, R_prev)`` hold the most that would have ended within ε_p (the first such), with those
    attempts' map rows left in ``nb[b]``."""
    k = nb.shape[1]
    q1 = previous / scale
    best = 0
    best_count = -1
    for j in range(deltas.shape[0]):
        release_nearest(b, xs0, xs1, srow, nb, (d + deltas[j]) / scale, q1)
        count = 0
        for i in range(k):
            if succ[j, nb[b, i]]:
                count += 1
        if count > best_count:
            best = j
            best_count = count
    release_nearest(b, xs0, xs1, srow, nb, (d + deltas[best]) / scale, q1)
    for i in range(k):
        nb[b, i] = srow[nb[b, i]]
    return best


@jit
def release_update(b, scale, deltas, xs0, xs1, srow, succ, x, nb, e):
    """:class:`~magctl.control.release_model.ReleasePolicyLaw`'s update for trial ``b``: ``δ ← δ*(|e|, e + δ)`` (a
    finite ``e`` only)."""
    if math.isfinite(e):
        best = release_choose(b, scale, deltas, xs0, xs1, srow, succ, nb, abs(e), e + x[b, 0])
        x[b, 0] = deltas[best]


@jit
def release_output(b, params, state, outputs):
    """:class:`~magctl.control.release_model.ReleasePolicyLaw`: ``y = δ``."""
    x, nb = state
    y, = outputs
    y[b, 0] = x[b, 0]


@jit
def release_update_step(b, params, state, next_state, inputs, base, noise):
    """:class:`~magctl.control.release_model.ReleasePolicyLaw`: the next attempt's ``δ`` from the last one's error."""
    scale, deltas, xs0, xs1, srow, succ = params
    x, nb = state
    nx, nnb = next_state
    e, = inputs
    nx[b, 0] = x[b, 0]
    for i in range(nb.shape[1]):
        nnb[b, i] = nb[b, i]
    release_update(b, scale, deltas, xs0, xs1, srow, succ, nx, nnb, e[b, 0])
