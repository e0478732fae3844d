"""Compiled sphere sub-steps: one frame of :class:`magctl.plant.sphere.Spheres`, the block's only implementation.

The numpy array form (``RefSpheres`` in ``tests/reference/plant_blocks.py``, the reference this module is
tested against) makes about 150 numpy calls per sub-step; at the batch sizes of a study (≈ 100 trials)
each call is dominated by its fixed cost, not by the arithmetic. This module runs the same frame — flow
look-up in the robot-frame map, inertia-free move ``V_p = k U`` (eq 4), gap balance (eq 8–9; in the
``accurate`` mode with Brenner's and Goren & O'Neill's wall factors, ``Spheres._gap_rate``),
non-penetration of the footprint and between spheres — as one numba-compiled loop over spheres and
sub-steps per trial, with the same operations in the same order. One trial's frame is
:func:`trial_frame`; the block's kernel (:func:`spheres_output`, :func:`spheres_update`, the convention of
:mod:`magctl.core.kernel`) calls it for the trial it is given, in both engines (the interpreted one
through :mod:`magctl.core.kernel_driver`); :func:`sphere_frame` calls it for every trial of a batch.

Off the flow map it sums the flow's far-field point forces (``RobotFlow.points/forces``)
as Blake Stokeslets — singular ones (``eps = 0``) for the boundary-element flow — as the
array form does. Both drag modes are compiled for a sphere at any gap: the ``paper`` mode's
eq 4–5, and the ``accurate`` mode's tabulated resistance functions
(:func:`wall_functions`: the spline of ``models/wall_resistance.toml`` passed in as the arrays of
:class:`magctl.plant.fluid.wall_drag.WallTable`, and the near-contact expansions, reflections and
blend of :mod:`magctl.plant.fluid.wall_drag`, whose shared definitions are compiled here unchanged).

numba's on-disk cache of this module is keyed on this file only: after editing the formulas it
compiles from ``wall_drag.py`` (``near_contact_terms``, ``far_field_terms``, ``smoothstep``,
``blend``), delete ``magctl/plant/__pycache__/sphere_kernel*.nb*`` (the kernel tests would
otherwise fail against the edited reference).
"""

from __future__ import annotations

import numba
import numpy as np

from magctl.plant.fluid.lubrication import film_gap
from magctl.plant.fluid.wall_drag import (
    ROT_BOUND,
    SHEAR_CONTACT,
    STAGNATION_CONTACT,
    blend,
    far_field_terms,
    near_contact_terms,
    smoothstep,
)

jit = numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
heavy = numba.njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
"""A frame too large to inline: compiled once, called (inlining it would multiply compile time)."""

# a push-out pass counts a centre as touching below this fraction of R (the array form's tolerance)
_TOUCH = 1.0 - 1e-9


@jit
def _stokeslet_term(f0, f1, f2, r0, r1, r2, b0, b1, b2, d3, w_direct, ib, ib3, ib5, c_g, h):
    """One unit motion's share of a Blake Stokeslet at ``r`` (from the point) and ``big`` (from its image):
    the increments of ``(u_x, u_y, u_z)`` and the image's extra vertical term."""
    g0, g1, g2 = f0, f1, -f2                             # the mirrored force
    rf = r0 * f0 + r1 * f1 + r2 * f2
    rrf = b0 * f0 + b1 * f1 + b2 * f2
    rrg = b0 * g0 + b1 * g1 + b2 * g2
    w_r = rf / d3
    w_big = -rrf * ib3 + 6 * h * (b2 - h) * ib5 * rrg - 2 * h * ib3 * g2
    return (w_direct * f0 - ib * f0 + c_g * g0 + w_r * r0 + w_big * b0,
            w_direct * f1 - ib * f1 + c_g * g1 + w_r * r1 + w_big * b1,
            w_direct * f2 - ib * f2 + c_g * g2 + w_r * r2 + w_big * b2,
            2 * h * ib3 * rrg)


@jit
def _stokeslet_flow(px, py, pz, vbx, vby, points, forces, eps, viscosity):
    """Flow at robot-frame ``(px, py, pz)`` summed over the flow's far-field (regularised) Blake Stokeslets
    (``magctl.plant.fluid.stokes.regularized_blake_velocity``, term by term), for body velocity
    ``(vbx, vby)`` as the combination of the two unit motions."""
    e2 = eps * eps
    ux0 = uy0 = uz0 = ux1 = uy1 = uz1 = 0.0
    for m in range(points.shape[0]):
        h = points[m, 2]
        r0, r1, r2 = px - points[m, 0], py - points[m, 1], pz - h
        b0, b1, b2 = r0, r1, pz + h                      # from the image point (y1, y2, -h)
        r2s = r0 * r0 + r1 * r1 + r2 * r2
        big2 = b0 * b0 + b1 * b1 + b2 * b2
        d3 = (r2s + e2) ** 1.5
        ib = 1.0 / np.sqrt(big2)
        ib3 = ib * ib * ib
        ib5 = ib3 * ib * ib
        w_direct = (r2s + 2 * e2) / d3
        c_g = 2 * h * (h - b2) * ib3
        a0, a1, a2, extra = _stokeslet_term(forces[0, m, 0], forces[0, m, 1], forces[0, m, 2], r0, r1, r2,
                                            b0, b1, b2, d3, w_direct, ib, ib3, ib5, c_g, h)
        ux0 += a0
        uy0 += a1
        uz0 += a2
        uz0 += extra
        a0, a1, a2, extra = _stokeslet_term(forces[1, m, 0], forces[1, m, 1], forces[1, m, 2], r0, r1, r2,
                                            b0, b1, b2, d3, w_direct, ib, ib3, ib5, c_g, h)
        ux1 += a0
        uy1 += a1
        uz1 += a2
        uz1 += extra
    scale = 8.0 * np.pi * viscosity
    return ((vbx * ux0 + vby * ux1) / scale, (vbx * uy0 + vby * uy1) / scale, (vbx * uz0 + vby * uz1) / scale)


@jit
def _bilinear(flat, c, nx, j, w00, w01, w10, w11):
    return w00 * flat[c, j] + w01 * flat[c + 1, j] + w10 * flat[c + nx, j] + w11 * flat[c + nx + 1, j]


@jit
def _flow_at(x, y, vbx, vby, flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height):
    """Flow ``(u_x, u_y, u_z)`` at robot-frame ``(x, y)`` for body velocity ``(vbx, vby)``: bilinear
    in the map, summed directly beyond it (``RobotFlow.lookup_components``)."""
    nx, ny = gx.shape[0], gy.shape[0]
    if abs(x) > gx[nx - 1] or abs(y) > gy[ny - 1]:
        return _stokeslet_flow(x, y, height, vbx, vby, points, forces, eps, viscosity)
    ix = min(max(np.searchsorted(gx, x) - 1, 0), nx - 2)
    iy = min(max(np.searchsorted(gy, y) - 1, 0), ny - 2)
    tx = (x - gx[ix]) / dgx[ix]
    ty = (y - gy[iy]) / dgy[iy]
    sx, sy = 1 - tx, 1 - ty
    w00, w01, w10, w11 = sx * sy, tx * sy, sx * ty, tx * ty
    c = iy * nx + ix
    m0 = _bilinear(flat, c, nx, 0, w00, w01, w10, w11)
    m1 = _bilinear(flat, c, nx, 1, w00, w01, w10, w11)
    m2 = _bilinear(flat, c, nx, 2, w00, w01, w10, w11)
    m3 = _bilinear(flat, c, nx, 3, w00, w01, w10, w11)
    m4 = _bilinear(flat, c, nx, 4, w00, w01, w10, w11)
    m5 = _bilinear(flat, c, nx, 5, w00, w01, w10, w11)
    return m0 * vbx + m3 * vby, m1 * vbx + m4 * vby, m2 * vbx + m5 * vby


@jit
def _paper_mobility(radius, gap, roughness):
    """V_p/U of eq 4 with eq 5 (``magctl.plant.fluid.wall_drag.paper_mobility``) at one gap."""
    h = radius + gap + roughness
    lg = np.log((gap + roughness) / radius)
    f_shear = 1.0 + 0.7005 * radius / h
    f_trans = min(8.0 / 15.0 * lg - 0.9588, -1.0)
    f_rot = max(-2.0 / 15.0 * lg - 0.2526, 0.0)
    q = radius / h
    w = -2.375e-6 * np.exp(12.05 * q) + 1.025 * np.exp(-0.1438 * q)
    rot = min(max(w, 0.0), ROT_BOUND)
    return -f_shear / (f_trans + rot * f_rot)


@jit
def wall_functions(d, table, out):
    """The accurate mode's eight functions ``(f_t, f_r, t_t, t_r, f_s, t_s, λ, g)`` at one δ/a = ``d``
    into ``out (8,)``, with the steps of ``magctl.plant.fluid.wall_drag._evaluate`` for one gap:
    the cubic spline of ln|f| in ln δ/a (evaluated as scipy's ``PPoly``: interval by bisection,
    ``c3 + c2 s + c1 s² + c0 s³`` summed in that order), blended below the table with the
    near-contact expansions (Chaoui & Feuillebois 2003; Cox & Brenner 1967) and above it with the
    reflections (Faxén; Goldman, Cox & Brenner 1967a,b; Lorentz).

    ``table`` is a :class:`~magctl.plant.fluid.wall_drag.WallTable` (a tuple of its fields).
    """
    knots, coef, signs, near_lo, near_hi, far_lo, far_hi = table
    lx = np.log(d)
    x = min(max(lx, near_lo), far_hi)
    n = knots.shape[0]
    i = min(max(np.searchsorted(knots, x, side="right") - 1, 0), n - 2)
    s = x - knots[i]
    s2 = s * s
    s3 = s2 * s
    for j in range(8):
        c = coef[j, i]
        v = 0.0 + c[3]
        v = v + c[2] * s
        v = v + c[1] * s2
        v = v + c[0] * s3
        out[j] = signs[j] * np.exp(v)
    if lx < near_hi:
        w = 1.0 - smoothstep(lx, near_lo, near_hi)
        f_t, f_r, t_t, t_r, lam = near_contact_terms(d)
        out[0] = blend(w, f_t, out[0])
        out[1] = blend(w, f_r, out[1])
        out[2] = blend(w, t_t, out[2])
        out[3] = blend(w, t_r, out[3])
        out[4] = blend(w, SHEAR_CONTACT[0], out[4])
        out[5] = blend(w, SHEAR_CONTACT[1], out[5])
        out[6] = blend(w, lam, out[6])
        out[7] = blend(w, STAGNATION_CONTACT, out[7])
    if lx > far_lo:
        w = smoothstep(lx, far_lo, far_hi)
        far = far_field_terms(d)
        for j in range(8):
            out[j] = blend(w, far[j], out[j])


@jit
def accurate_state(radius, gap, roughness, table, out):
    """V_p/U, λ and g of a sphere at gap δ in the ``accurate`` mode, at δ/a = (δ + ε)/R
    (``wall_drag.accurate_mobility`` and ``wall_drag.normal_factors``: the free-sphere force and
    torque balance of Goldman, Cox & Brenner 1967b; Brenner's 1961 normal drag factor; Goren &
    O'Neill's 1971 wall-flow factor). ``out (8,)`` is scratch for :func:`wall_functions`."""
    wall_functions((gap + roughness) / radius, table, out)
    f_t, f_r, t_t, t_r, f_s, t_s = out[0], out[1], out[2], out[3], out[4], out[5]
    half = 0.5 * radius / (radius + gap + roughness)
    det = f_t * t_r - f_r * t_t
    return (-f_s * t_r + f_r * half * t_s) / det, out[6], out[7]


@jit
def translation_resistance(radius, gap, roughness, table, out):
    """ζ/(6πμR) of a torque-free sphere translating along the glass at gap δ (δ/a = (δ + ε)/R):
    ``|f_t − f_r t_t / t_r|`` of the accurate mode's resistance functions (Goldman, Cox & Brenner 1967a:
    with the torque-balance ``t_t V + t_r aΩ = 0`` the force is ``6πμa V (f_t t_r − f_r t_t)/t_r``)."""
    wall_functions((gap + roughness) / radius, table, out)
    f_t, f_r, t_t, t_r = out[0], out[1], out[2], out[3]
    return abs((f_t * t_r - f_r * t_t) / t_r)


@jit
def _nearest_edge(px, py, x0, y0, dx, dy, ab2, y1):
    """Distance from robot-frame ``(px, py)`` to the polygon, the nearest point ``(qx, qy)``, its edge and
    whether the point lies inside."""
    best, bx, by, edge = np.inf, 0.0, 0.0, 0
    crossings = 0
    for e in range(x0.shape[0]):
        t = min(max(((px - x0[e]) * dx[e] + (py - y0[e]) * dy[e]) / ab2[e], 0.0), 1.0)
        qx, qy = x0[e] + t * dx[e], y0[e] + t * dy[e]
        ex, ey = px - qx, py - qy
        d2 = ex * ex + ey * ey
        if d2 < best:
            best, bx, by, edge = d2, qx, qy, e
        if (y0[e] > py) != (y1[e] > py) and px < x0[e] + (py - y0[e]) * dx[e] / dy[e]:
            crossings += 1
    return np.sqrt(best), bx, by, edge, crossings % 2 == 1


@jit
def _film_velocity(v, rel, vel, turn, gi, m, footprint, film, radius, roughness, viscosity, tau, table, scratch):
    """The sphere's velocity ``v`` (world, complex) with the lubrication between it and the robot
    (:mod:`magctl.plant.fluid.lubrication`: the face film or the edge law of the nearest footprint edge): its
    component along the outline's normal replaced by the one that advances the gap exactly over the sub-step
    (:func:`~magctl.plant.fluid.lubrication.film_gap`). ``rel`` is the centre in the robot frame at the
    sub-step's start, ``vel`` the robot's velocity, ``m`` the sphere's mobility multiplier. Returns the
    velocity and whether the gap closed to rough contact."""
    x0, y0, dx, dy, ab2, y1, area, log_coef = footprint
    h_min, h_face, h_edge = film
    dist, qx, qy, e, inside = _nearest_edge(rel.real, rel.imag, x0, y0, dx, dy, ab2, y1)
    if inside or dist <= 0.0:
        return v, False
    h = max(dist - radius, h_min)
    face = area[e] > 0.0 and h < h_face
    edge = log_coef[e] > 0.0 and h < h_edge
    if not (face or edge):
        return v, False
    n = complex((rel.real - qx) / dist, (rel.imag - qy) / dist) * turn      # robot → sphere, world frame
    zeta = 6.0 * np.pi * viscosity * radius * translation_resistance(radius, gi, roughness, table, scratch) / m
    k_face = 6.0 * np.pi * viscosity * area[e] / zeta
    k_edge = 6.0 * np.pi * viscosity * log_coef[e] / zeta
    un = (vel * n.conjugate()).real
    vn = (v * n.conjugate()).real
    h1 = film_gap(h, (vn - un) * tau, k_face, h_face, k_edge, h_edge, h_min)
    closed = h1 <= h_min and vn < un       # the robot drives the outline into the sphere
    return v + (un + (h1 - h) / tau - vn) * n, closed


@jit
def _push_out_point(px, py, x0, y0, dx, dy, ab2, y1, radius, iterations):
    """One circle centre (robot frame) moved off the polygon: up to ``iterations`` passes of
    nearest-edge projection, as ``magctl.plant.sphere._push_out``. Returns ``x, y, touched``."""
    touched = False
    for _ in range(iterations):
        dist, bx, by, _, inside = _nearest_edge(px, py, x0, y0, dx, dy, ab2, y1)
        if not (inside or dist < radius * _TOUCH):
            break
        touched = True
        d = max(dist, 1e-15)
        sign = -1.0 if inside else 1.0
        px = bx + ((px - bx) / d * sign) * radius
        py = by + ((py - by) / d * sign) * radius
    return px, py, touched


@jit
def _separate(xy, b, radius, iterations, cx, cy):
    """Overlapping spheres of trial ``b`` pushed apart half each (``separate_spheres``): centres
    ``xy[b] = (x₀, y₀, x₁, y₁, …)``, updated in place; ``cx, cy`` hold a pass's corrections (one per pair)."""
    n = xy.shape[1] // 2
    for _ in range(iterations):
        any_overlap = False
        k = 0
        for i in range(n):
            for j in range(i + 1, n):
                ddx, ddy = xy[b, 2 * j] - xy[b, 2 * i], xy[b, 2 * j + 1] - xy[b, 2 * i + 1]
                dist = np.sqrt(ddx * ddx + ddy * ddy)
                overlap = 2 * radius - dist
                if dist > 1e-12:
                    ux, uy = ddx / dist, ddy / dist
                else:   # no usable centre line: part them along x
                    ux, uy = 1.0, 0.0
                if overlap > 0:
                    any_overlap = True
                    cx[k], cy[k] = 0.5 * overlap * ux, 0.5 * overlap * uy
                else:
                    cx[k], cy[k] = 0.0, 0.0
                k += 1
        if not any_overlap:
            break
        k = 0
        for i in range(n):
            for j in range(i + 1, n):
                xy[b, 2 * i] = xy[b, 2 * i] - cx[k]
                xy[b, 2 * i + 1] = xy[b, 2 * i + 1] - cy[k]
                xy[b, 2 * j] = xy[b, 2 * j] + cx[k]
                xy[b, 2 * j + 1] = xy[b, 2 * j + 1] + cy[k]
                k += 1


@heavy
def trial_frame(b, xy, gap, mult, pos, vel, turn, frame, flow, footprint, table, work):
    """One frame of ``n_sub`` sub-steps for trial ``b``'s spheres, in place; returns whether some
    sphere touched the robot. Every sub-step: the flow at each centre (map in the robot frame, or
    the Stokeslets off it), the inertia-free move ``V_p = k U`` of eq 4 with the mobility capped at
    the free-sphere limit 1, the gap balance of eq 8–9, then non-penetration of the footprint and
    between spheres (the reference ``RefSpheres.update``, the same operations in the same order).

    ``xy (B, 2N)`` centres ``(x₀, y₀, x₁, …)`` [m], ``gap (B, N)`` δ [m], ``mult (B, N)`` mobility
    multipliers; ``pos, vel, turn`` the robot's position, held velocity and ``e^{iθ}`` as complex
    numbers. The other arguments of :func:`sphere_frame` come in tuples (few arguments, so that the
    call can be inlined): ``frame = (n_sub, tau, radius, reach, box_x, box_y, sink_rate, held_rate,
    adhesion_range, k_contact, paper_mode, roughness, inv_lambda_contact, flow_push_contact, film)``,
    ``flow = (flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height)``, ``footprint = (x0, y0,
    dx, dy, ab2, y1, area, log_coef)`` (per edge, the face film's ``A`` and the edge law's ``aC``,
    :func:`~magctl.plant.fluid.lubrication.film_laws`), the wall ``table``, and ``work = (cx, cy, scratch)``:
    work arrays, one correction per sphere pair and ``(8,)`` for :func:`wall_functions`. ``film = (h_min,
    h_face, h_edge)``: the face film acts below ``h_face``, the edge law below ``h_edge``, and either closes
    to rough contact at ``h_min`` (both cut-offs 0: no lubrication, as in the ``paper`` mode).
    """
    (n_sub, tau, radius, reach, box_x, box_y, sink_rate, held_rate, adhesion_range, k_contact, paper_mode,
     roughness, inv_lambda_contact, flow_push_contact, film) = frame
    flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height = flow
    x0, y0, dx, dy, ab2, y1, _, _ = footprint
    cx, cy, scratch = work
    n = gap.shape[1]
    back = turn.conjugate()
    vb = vel * back
    touched = False
    for k in range(n_sub):
        p_start = pos + vel * (k * tau)
        p_mid = pos + vel * (k + 0.5) * tau
        p_end = pos + vel * (k + 1.0) * tau
        for i in range(n):
            zi = complex(xy[b, 2 * i], xy[b, 2 * i + 1])
            gi = gap[b, i]
            rel = (zi - p_mid) * back
            ux, uy, uz = _flow_at(rel.real, rel.imag, vb.real, vb.imag, flat, gx, gy, dgx, dgy,
                                  points, forces, eps, viscosity, height)
            settle = held_rate if gi <= adhesion_range else sink_rate
            # mobility (eq 4) and gap rate (eq 8-9) at the gap the sub-step starts from
            if paper_mode:
                k_now = k_contact if gi <= 0 else _paper_mobility(radius, gi, roughness)
                rate = uz - settle
            elif gi <= 0:    # accurate mode on the glass: (g U_z − settling) / λ at δ = 0
                k_now = k_contact
                rate = (flow_push_contact * uz - settle) * inv_lambda_contact
            else:            # accurate mode, lifted: the tabulated functions at (δ + ε)/R
                k_now, lam, push = accurate_state(radius, gi, roughness, table, scratch)
                rate = (push * uz - settle) * (1.0 / lam)
            # capped at the free-sphere limit 1
            v = min(k_now * mult[b, i], 1.0) * (complex(ux, uy) * turn)
            if film[1] > 0.0 or film[2] > 0.0:
                d0 = zi - p_start
                if abs(d0) < reach + max(film[1], film[2]):
                    v, closed = _film_velocity(v, d0 * back, vel, turn, gi, mult[b, i], footprint, film, radius,
                                               roughness, viscosity, tau, table, scratch)
                    touched = touched or closed
            zi += v * tau
            xy[b, 2 * i] = zi.real
            xy[b, 2 * i + 1] = zi.imag
            gap[b, i] = max(gi + rate * tau, 0.0)
        for i in range(n):
            d = complex(xy[b, 2 * i], xy[b, 2 * i + 1]) - p_end
            if abs(d) >= reach:
                continue
            rel = d * back
            if not (abs(rel.real) < box_x and abs(rel.imag) < box_y):
                continue
            rx, ry, hit = _push_out_point(rel.real, rel.imag, x0, y0, dx, dy, ab2, y1, radius, 3)
            if hit:
                zi = p_end + complex(rx, ry) * turn
                xy[b, 2 * i] = zi.real
                xy[b, 2 * i + 1] = zi.imag
                touched = True
        if n > 1:
            _separate(xy, b, radius, 3, cx, cy)
    return touched


@numba.njit(cache=True, nogil=True, error_model="numpy")
def sphere_frame(xy, gap, mult, pos, vel, turn, n_sub, tau, flat, gx, gy, dgx, dgy, points, forces, eps,
                 viscosity, height,
                 x0, y0, dx, dy, ab2, y1, area, log_coef, radius, reach, box_x, box_y, sink_rate, held_rate,
                 adhesion_range, k_contact, paper_mode, roughness, inv_lambda_contact, flow_push_contact, h_min,
                 h_face, h_edge, table):
    """Advance every trial's spheres by one frame of ``n_sub`` sub-steps, in place (:func:`trial_frame`
    per trial).

    Parameters
    ----------
    xy : float (B, 2N)
        Sphere centres ``(x₀, y₀, x₁, y₁, …)`` [m]; overwritten.
    gap : float (B, N)
        Gaps δ [m]; overwritten.
    mult : float (B, N)
        Per-sphere mobility multiplier (sticky patches, release scatter).
    pos, vel, turn : complex (B,)
        Robot position, velocity (held over the frame) and ``e^{iθ}`` of its heading.
    flat, gx, gy, dgx, dgy
        The flow maps as one ``(ny·nx, 6)`` table and the grid (``RobotFlow._flat_maps``).
    points, forces, eps, viscosity, height
        The flow's far-field point forces (``RobotFlow``), for spheres off the map.
    x0, y0, dx, dy, ab2, y1, area, log_coef
        Footprint edges (:class:`~magctl.plant.outline.Polygon`), the face film's ``A`` and the edge
        law's ``aC`` per edge (:func:`~magctl.plant.fluid.lubrication.film_laws`).
    sink_rate, held_rate : float
        ``W_b/ζ`` and ``(W_b + P)/ζ`` of eq 8–9 [m/s]; the adhesion ``P`` acts within
        ``adhesion_range`` of the glass.
    k_contact, paper_mode, roughness
        V_p/U on the glass, whether the drag mode is ``paper`` (eq 4–5), and ε [m].
    inv_lambda_contact, flow_push_contact : float
        1/λ and g of the gap balance on the glass in the ``accurate`` mode (Brenner's normal drag
        factor and Goren & O'Neill's wall-flow factor at δ = 0, ``Spheres._gap_rate``); unused in
        the ``paper`` mode (eq 9 as printed).
    h_min, h_face, h_edge : float
        The robot–sphere gap closes to rough contact at ``h_min``; the face film acts below ``h_face``,
        the edge law below ``h_edge`` [m] (both 0: no lubrication).
    table : WallTable
        The ``accurate`` mode's resistance functions (:func:`wall_functions`), for lifted spheres and the
        film; unused in the ``paper`` mode.

    Returns
    -------
    contact : bool (B,)
        Some sphere touched the robot during the frame.
    """
    batch, n = gap.shape
    contact = np.zeros(batch, np.bool_)
    npair = max(n * (n - 1) // 2, 1)
    cx = np.empty(npair)
    cy = np.empty(npair)
    scratch = np.empty(8)
    frame = (n_sub, tau, radius, reach, box_x, box_y, sink_rate, held_rate, adhesion_range, k_contact, paper_mode,
             roughness, inv_lambda_contact, flow_push_contact, (h_min, h_face, h_edge))
    flow = (flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height)
    footprint = (x0, y0, dx, dy, ab2, y1, area, log_coef)
    work = (cx, cy, scratch)
    for b in range(batch):
        contact[b] = trial_frame(b, xy, gap, mult, pos[b], vel[b], turn[b], frame, flow, footprint, table, work)
    return contact


# --- the block's kernel (magctl.core.kernel convention: one trial per call) ----------------------------------
@jit
def spheres_output(b, params, state, outputs):
    """``Spheres.output``: the centres and the contact flag of the state."""
    xy, gap, mult, contact = state
    spheres, touching = outputs
    for i in range(xy.shape[1]):
        spheres[b, i] = xy[b, i]
    touching[b, 0] = contact[b, 0]


@jit
def spheres_update(b, params, state, next_state, inputs, base, noise):
    """``Spheres.update``: one frame of trial ``b`` by :func:`trial_frame` (the heading's ``e^{iθ}`` as
    the reference forms it). No draws: the mobility multipliers are drawn at step 0."""
    (n_sub, tau, flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height, x0, y0, dx, dy, ab2, y1, area,
     log_coef, radius, reach, box_x, box_y, sink_rate, held_rate, adhesion_range, k_contact, paper_mode, roughness,
     inv_lambda_contact, flow_push_contact, h_min, h_face, h_edge, knots, coef, signs, near_lo, near_hi, far_lo, far_hi,
     cx, cy, scratch) = params
    xy, gap, mult, contact = state
    nxy, ngap, nmult, ncontact = next_state
    position, heading, velocity = inputs
    for i in range(xy.shape[1]):
        nxy[b, i] = xy[b, i]
    for i in range(gap.shape[1]):
        ngap[b, i] = gap[b, i]
        nmult[b, i] = mult[b, i]
    h = heading[b, 0]
    turn = complex(np.cos(h), np.sin(h))
    pos = complex(position[b, 0], position[b, 1])
    vel = complex(velocity[b, 0], velocity[b, 1])
    frame = (n_sub, tau, radius, reach, box_x, box_y, sink_rate, held_rate, adhesion_range, k_contact, paper_mode,
             roughness, inv_lambda_contact, flow_push_contact, (h_min, h_face, h_edge))
    flow = (flat, gx, gy, dgx, dgy, points, forces, eps, viscosity, height)
    footprint = (x0, y0, dx, dy, ab2, y1, area, log_coef)
    table = (knots, coef, signs, near_lo, near_hi, far_lo, far_hi)
    ncontact[b, 0] = trial_frame(b, nxy, ngap, nmult, pos, vel, turn, frame, flow, footprint, table,
                                 (cx, cy, scratch))
